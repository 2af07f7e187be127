"""``nn.Module`` classes: spiking pooling (and the layers built on it), the spiking classifier."""

from evdown_torch.models.classifier import ClassifierState, SpikingClassifier
from evdown_torch.models.pooling import SpikingPooling, SpikingPoolingLayer, reset_states

__all__ = [
    "ClassifierState",
    "SpikingClassifier",
    "SpikingPooling",
    "SpikingPoolingLayer",
    "reset_states",
]
