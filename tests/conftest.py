import os

os.environ.setdefault("MUJOCO_GL", "egl")

import pytest
from omegaconf import OmegaConf

from hvc.config import compose

ENV_TASKS = ("go_to_target", "walls", "gaps", "forage", "heterogeneous_forage")


def plain_cfg(*overrides: str):
    """(task, body, render) dicts of a composed config, as the env code receives them."""
    cfg = compose(list(overrides))
    return tuple(OmegaConf.to_container(cfg[k], resolve=True) for k in ("task", "body", "render"))


@pytest.fixture
def cfg_dicts():
    return plain_cfg
