"""The trade study behind ``evdown evaluate``."""
