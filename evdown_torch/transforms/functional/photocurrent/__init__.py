"""Photocurrent pooling (method 7): events to video to events.

``settings`` holds what both modes share, ``events_mode`` and ``sums`` the events mode,
``frames_mode`` the paper's literal frames pipeline, and ``method`` the three kernels that
pick the mode.
"""
