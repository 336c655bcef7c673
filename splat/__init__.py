"""splat package."""

import mvgeo.common.deps  # noqa: F401  (cv2 before pycolmap: docs/conventions.md)
