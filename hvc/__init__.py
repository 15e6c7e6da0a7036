"""hvc: hierarchical visuomotor control of humanoids (Merel et al., ICLR 2019)."""
import os

if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"  # headless default, before anything imports mujoco; a user's choice wins

# torch's OpenMP threads sleep when idle instead of spinning: a learner with torch_threads=2
# beside another busy process otherwise slows down several-fold (docs/results/design_measurements)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
