"""Change detection (the paper's section 5): which features of the partially correct a priori model are
unchanged, moved, altered or missing, and what is new, given a registered scan (:mod:`.detection`)."""

from .detection import (
    PIXEL_BEHIND,
    PIXEL_EXPLAINED,
    PIXEL_FRONT,
    PIXEL_NONE,
    PIXEL_OTHER_SURFACE,
    ChangeParams,
    ChangeResult,
    FeatureChange,
    classify_pixels,
    detect_changes,
    object_label,
    pixel_allowance,
)

__all__ = [
    "PIXEL_BEHIND", "PIXEL_EXPLAINED", "PIXEL_FRONT", "PIXEL_NONE", "PIXEL_OTHER_SURFACE",
    "ChangeParams", "ChangeResult",
    "FeatureChange", "classify_pixels", "detect_changes", "object_label", "pixel_allowance",
]
