"""Tests of evdown_torch.data: preprocessing a dataset into a cache and reading it back."""
