"""Spiking ``nn.Module``s."""

from evdown_torch.models.classifier import ClassifierState, SpikingClassifier

__all__ = ["ClassifierState", "SpikingClassifier"]
