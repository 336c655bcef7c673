"""Multi-view geometry: cameras, transforms, two-view geometry, triangulation,
pose metrics and pose-free alignment. Conventions: docs/conventions.md."""

import mvgeo.common.deps  # noqa: F401  (cv2 before pycolmap)
