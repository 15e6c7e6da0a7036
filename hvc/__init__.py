"""hvc: hierarchical visuomotor control of humanoids (Merel et al., ICLR 2019)."""
import os

if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"  # headless default, before anything imports mujoco; a user's choice wins

__version__ = "0.1.0"
