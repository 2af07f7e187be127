"""Reading drawn figures back."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def big_blobs(rgb: np.ndarray) -> int:
    """Connected non-white areas larger than text: the panels of a drawn figure."""
    mask = rgb[..., :3].min(axis=2) < 200
    labels, _ = ndimage.label(mask)
    sizes = np.bincount(labels.ravel())[1:]
    return int((sizes > 2000).sum())
