"""Small, fast scenes for camera tests (the repository's grade-1 scene, shortened)."""

from __future__ import annotations

from typing import Any

from stipi_daemon.sim.scene import Scene, load_scene
from tests.conftest import REPO_ROOT


def small_scene(
    *, fps: float = 60.0, recovery_s: float = 1.0, effects: list[dict[str, Any]] | None = None
) -> Scene:
    """grade1 at 64x48 px, 0.2 s approach + 0.5 s hold + ``recovery_s`` recovery."""
    scene = load_scene(REPO_ROOT / "configs" / "scenes" / "grade1.yaml")
    profile = scene.force_profile.model_copy(
        update={"approach_s": 0.2, "hold_s": 0.5, "recovery_s": recovery_s}
    )
    scene = scene.model_copy(update={"force_profile": profile})
    scene = scene.with_camera(width=64, height=48, fps=fps)
    if effects:
        scene = scene.with_effects(effects)
    return scene
