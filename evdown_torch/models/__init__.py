"""``nn.Module``s: spiking pooling (and the layers built on it)."""

from evdown_torch.models.pooling import SpikingPooling

__all__ = ["SpikingPooling"]
