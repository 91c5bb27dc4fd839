from __future__ import annotations

from tests.scene.conftest import planar_rm, tunnel_rm  # noqa: F401  (shared mesh fixtures)
