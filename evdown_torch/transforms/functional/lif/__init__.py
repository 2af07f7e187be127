"""LIF pooling (method 6), event-driven.

``settings`` holds the neuron's settings, ``steps`` the clock, ``pooling`` the whole-stream
kernel, ``keys`` the grouping of events into cells and the order of the spikes, ``rounds``
snntorch's update at every touched cell, ``closed_form`` the spikes between firings without
rounds, ``chains`` the neuron without input, and ``stream`` the session's state between
chunks.
"""
