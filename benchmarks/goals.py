"""The project's speed and memory goals, checked against a benchmark run's ``results.json``.

Run: ``python benchmarks/goals.py DIR/results.json`` prints the goals table (Markdown) of a
run of ``evdown bench`` (or ``benchmarks/bench_all.py``, which prints it at the end). The goals
come from the project's issues and the paper's figures; they are not part of the installed
package.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

from evdown_torch.bench import BenchResults, load_results

#: The paper's reference code, seconds per 100,000 events (issue 3).
PAPER_SECONDS_PER_100K = {"event_count": 0.8, "linear": 2.6, "cubic": 2.9}


@dataclass(frozen=True)
class Goal:
    """A speed or memory goal stated in an issue.

    ``kind`` is ``"rate"`` (events/s on the headline stream at factor 4, ``value`` the
    minimum), ``"peer"`` (throughput ratio to peer ``peer``, ``value`` the minimum) or
    ``"memory"`` (process peak on the large stream at factor 4, ``value`` the maximum bytes).
    """

    issue: int
    method: str
    kind: str
    value: float
    text: str
    peer: str = ""


GOALS: tuple[Goal, ...] = (
    Goal(2, "downsample", "peer", 0.5, ">= 0.5x tonic Downsample's throughput",
         "tonic_downsample"),
    Goal(2, "funnelling", "rate", 10e6, ">= 10 M events/s"),
    Goal(3, "event_count", "rate", 10e6, ">= 10 M events/s"),
    Goal(3, "linear", "rate", 3e6, ">= 3 M events/s"),
    Goal(3, "cubic", "rate", 1e6, ">= 1 M events/s"),
    Goal(5, "lif", "rate", 2e6, ">= 2 M events/s (dt = 1 ms)"),
    *(Goal(3, name, "memory", 4e9, "peak < 4 GB on 1280x720, 10M events")
      for name in ("downsample", "funnelling", "event_count", "linear", "cubic", "lif")),
)


def evaluate_goals(results: BenchResults) -> list[dict[str, str]]:
    """Each goal of a method that was measured: its figure and whether it is met."""
    rows = []
    headline, large = results.input("gesture"), results.input("large")
    measured = {m.candidate for m in results.measurements}
    for goal in GOALS:
        if goal.method not in measured:
            continue
        row = {"issue": str(goal.issue), "method": goal.method, "goal": goal.text,
               "measured": "n/a", "status": ""}
        if goal.kind == "memory":
            m = results.find("methods", "large", goal.method, 4)
            small = large is not None and large.num_events < 10_000_000
            if m is None or m.peak_total is None:
                row["status"] = "not measured" + (f" ({m.note})" if m and m.note else "")
            else:
                row["measured"] = f"{m.peak_total / 1e9:.2f} GB"
                over = m.peak_total / goal.value - 1
                row["status"] = "met" if over <= 0 else f"missed by {over * 100:.0f}% (over)"
                if small:
                    row["status"] += f" (indicative: {large.num_events:,} events, not 10M)"
        else:
            m = results.find("methods", "gesture", goal.method, 4)
            small = headline is not None and headline.num_events < 1_000_000
            if m is None or m.rate is None:
                row["status"] = "not measured" + (f" ({m.note})" if m and m.note else "")
            elif goal.kind == "rate":
                cpu_rate = m.events_in / m.cpu_seconds if m.cpu_seconds else math.inf
                row["measured"] = (f"{m.rate / 1e6:.2f} M events/s ({cpu_rate / 1e6:.2f} on "
                                   "CPU time)")
                row["status"] = _status(m.rate >= goal.value, m.rate / goal.value)
                if m.rate < goal.value <= cpu_rate:
                    row["status"] += " (met on CPU time: the call waited for a busy core)"
            else:
                peer = results.find("methods", "gesture", goal.peer, 4)
                if peer is None or peer.rate is None:
                    row["status"] = "not measured (peer absent)"
                else:
                    ratio = m.rate / peer.rate
                    row["measured"] = f"{ratio:.2f}x"
                    row["status"] = _status(ratio >= goal.value, ratio / goal.value)
            paper = PAPER_SECONDS_PER_100K.get(goal.method)
            if m is not None and m.rate is not None and paper and goal.kind == "rate":
                row["measured"] += f"; {m.rate * paper / 1e5:,.0f}x the paper's code"
            if small and row["measured"] != "n/a":
                row["status"] += (f" (indicative: {headline.num_events:,} events, "
                                  "the goal's stream has 1M)")
        rows.append(row)
    return rows


def _status(met: bool, margin: float) -> str:
    return "met" if met else f"missed by {(1 - margin) * 100:.0f}%"


def goals_table(results: BenchResults) -> str:
    """The goals of the measured methods as a Markdown table."""
    lines = ["Rate goals: the `gesture` stream at factor 4, one thread. Memory goal: the "
             "`large` stream at factor 4, process peak.", "",
             "| issue | method | goal | measured | status |", "|---|---|---|---|---|"]
    for g in evaluate_goals(results):
        lines.append(f"| {g['issue']} | {g['method']} | {g['goal']} | {g['measured']} | "
                     f"{g['status']} |")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python benchmarks/goals.py DIR/results.json", file=sys.stderr)
        return 2
    print("## Goals\n\n" + goals_table(load_results(Path(argv[0]))))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
