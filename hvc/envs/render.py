"""CPU-friendly egocentric rendering with mujoco.Renderer.

dm_control's camera observables render with the model's full visual settings (shadows,
reflections, skybox, 4x anti-aliasing), which dominate a CPU render (llvmpipe). The fast
settings (conf/render/fast.yaml) keep textures and geometry and drop those (frame rates in
docs/results/design_measurements/). A Renderer owns a GL context, so create it in the
process that renders.
"""
from __future__ import annotations

import os
from typing import Any, Mapping

if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"  # headless default; a user's choice wins

import mujoco
import numpy as np

# dm_control's CMU humanoid geom groups: the bodycam hides the walker's own geoms,
# the head camera hides the invisible helper geoms (cmu_humanoid.py).
_WALKER_GEOM_GROUP = 2
_WALKER_INVIS_GROUP = 1

_FLAGS = {"shadows": mujoco.mjtRndFlag.mjRND_SHADOW, "reflections": mujoco.mjtRndFlag.mjRND_REFLECTION,
          "skybox": mujoco.mjtRndFlag.mjRND_SKYBOX, "haze": mujoco.mjtRndFlag.mjRND_HAZE,
          "fog": mujoco.mjtRndFlag.mjRND_FOG}


def apply_model_settings(model: mujoco.MjModel, settings: Mapping[str, Any]) -> None:
    """Settings read when a GL context is made: call before creating the Renderer."""
    if settings.get("antialias_samples") is not None:
        model.vis.quality.offsamples = int(settings["antialias_samples"])
    if settings.get("tessellation_slices") is not None:
        model.vis.quality.numslices = int(settings["tessellation_slices"])
    if settings.get("tessellation_stacks") is not None:
        model.vis.quality.numstacks = int(settings["tessellation_stacks"])


class CameraRenderer:
    """Renders one named camera of one model to uint8 RGB (height, width, 3)."""

    def __init__(self, model: mujoco.MjModel, camera: str, settings: Mapping[str, Any]):
        self.camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if self.camera_id < 0:
            names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]
            raise ValueError(f"camera {camera!r} not in the model; allowed: {', '.join(names)}")
        apply_model_settings(model, settings)
        self.renderer = mujoco.Renderer(model, int(settings["height"]), int(settings["width"]))
        self.option = mujoco.MjvOption()
        hidden = _WALKER_GEOM_GROUP if camera.endswith("bodycam") else _WALKER_INVIS_GROUP
        self.option.geomgroup[hidden] = 0
        self.option.flags[mujoco.mjtVisFlag.mjVIS_TEXTURE] = int(bool(settings.get("textures", True)))
        self.flags = {_FLAGS[k]: int(bool(settings[k])) for k in _FLAGS if settings.get(k) is not None}

    def render(self, data: mujoco.MjData, out: np.ndarray | None = None) -> np.ndarray:
        self.renderer.update_scene(data, camera=self.camera_id, scene_option=self.option)
        for flag, value in self.flags.items():
            self.renderer.scene.flags[flag] = value
        return self.renderer.render(out=out)

    def close(self) -> None:
        self.renderer.close()
