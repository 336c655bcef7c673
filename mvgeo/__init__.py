"""Multi-view geometry: cameras, transforms, two-view geometry, triangulation,
pose metrics and pose-free alignment. Conventions: docs/conventions.md.

Importing the package loads nothing heavy: `mvgeo.common` is the light shared base
(no cv2, pycolmap or torch; tests/common/test_import_light.py), and pycolmap is
reached only through `mvgeo.common.deps`, which imports cv2 first."""
