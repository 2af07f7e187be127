"""What the models share about snntorch neurons."""

from __future__ import annotations

import snntorch


def unregistered(neuron: snntorch.SpikingNeuron) -> snntorch.SpikingNeuron:
    """Take a neuron out of snntorch's class-level registry and return it.

    snntorch lists every neuron ever built in ``SpikingNeuron.instances`` for its hidden-state
    helpers. Our modules keep their state explicit and never use that registry; leaving a
    neuron in it would keep every discarded model alive.
    """
    instances = snntorch.SpikingNeuron.instances
    for i, other in enumerate(instances):
        if other is neuron:
            del instances[i]
            break
    return neuron
