"""The shared KEY=VALUE parser and factor parser/formatter."""

from __future__ import annotations

import math

import pytest

from evdown_torch._text import (
    format_factor,
    parse_factor,
    parse_setting,
    parse_settings,
    parse_value,
)


def test_values_are_literals_or_text():
    assert parse_value(" 3 ") == 3 and parse_value("1e3") == 1000.0
    assert parse_value("True") is True and parse_value("None") is None
    assert parse_value("inf") == math.inf and parse_value("-inf") == -math.inf
    assert parse_value("subtract") == "subtract" and parse_value("a b") == "a b"
    assert parse_value("(1, 2)") == (1, 2) and parse_value("") == ""


def test_settings_split_only_before_a_key():
    assert parse_settings("") == {}
    assert parse_settings("factor=(1, 2), tau=inf,reset-mechanism=zero") == {
        "factor": (1, 2), "tau": math.inf, "reset_mechanism": "zero"}
    assert parse_setting("name=a=b") == ("name", "a=b")
    for bad in ("threshold", "=3", " =3"):
        with pytest.raises(ValueError, match="KEY=VALUE"):
            parse_setting(bad)
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_settings("oops,dt=5")


def test_factors_round_trip_through_text():
    for factor in (1, 4, (4, 2), (1, 3)):
        assert parse_factor(format_factor(factor)) == factor
    assert format_factor((3, 3)) == "3" and format_factor([2, 5]) == "2x5"
    assert parse_factor(" 4 , 2 ") == (4, 2)
    for bad in ("", "4,", "a", "1,2,3", "2.5"):
        with pytest.raises(ValueError, match="factor must be F or FX,FY"):
            parse_factor(bad)
