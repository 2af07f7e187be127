"""``nn.Module``s: spiking pooling (and the layers built on it), the spiking classifier."""

from evdown_torch.models.classifier import ClassifierState, SpikingClassifier
from evdown_torch.models.pooling import SpikingPooling

__all__ = ["ClassifierState", "SpikingClassifier", "SpikingPooling"]
