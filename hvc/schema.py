"""Typed schemas of the `algorithm` and `controller` config groups, registered with Hydra's
ConfigStore: each group's YAML file names its schema first in its defaults list, so a key's
type and default are declared once, here, and a wrong type or an unknown key fails with
Hydra's own message (`algorithm.learning_rate=fast`). The learners take their
hyperparameters as these dataclasses (hvc.algorithms), so code and config cannot disagree.
Cross-field rules stay in hvc.config.validate.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, List, Mapping, Optional, TypeVar

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING


@dataclass
class AlgorithmConfig:
    name: str = MISSING
    _target_: str = MISSING          # the learner class (hvc.algorithms.learner.Learner)
    learning_rate: float = 1e-4      # Adam
    batch_size: int = 32             # unrolls per learner update
    updates_per_unroll: float = 1.0  # learner updates per unroll added to replay; fractions allowed


@dataclass
class VTraceConfig(AlgorithmConfig):
    entropy_cost: float = 0.01
    rho_clip: float = 1.0            # rho_bar
    c_clip: float = 1.0              # c_bar


@dataclass
class SVG0Config(AlgorithmConfig):
    kl_cost: float = 0.1             # eta, KL(pi || pi_target)
    target_update_period: int = 100  # learner steps between target refreshes
    entropy_cost: float = 1e-5       # A.3
    value_samples: int = 4           # samples of pi for E_pi Q(h', a) in the targets


@dataclass
class SVG0RetraceConfig(SVG0Config):
    retrace_lambda: float = 1.0


@dataclass
class WolpertingerConfig(SVG0Config):  # 1-step targets: no retrace_lambda
    kl_cost: float = 0.0


@dataclass
class ControllerConfig:
    name: str = MISSING
    _target_: str = MISSING          # the controller class (hvc.controllers.base.Controller)
    skills: str = "clip_set"         # none: drives the body itself; own: a policy of its own; clip_set: clips='s experts
    needs_humanoid: bool = True
    algorithms: List[str] = field(default_factory=list)  # the learners allowed to train it


@dataclass
class FragmentsControllerConfig(ControllerConfig):
    pass


@dataclass
class GaussianControllerConfig(ControllerConfig):
    sigma_clip: List[float] = field(default_factory=lambda: [0.1, 1.0])  # the Gaussian's sigma bounds


@dataclass
class EndToEndControllerConfig(GaussianControllerConfig):
    pass


@dataclass
class SteerableControllerConfig(GaussianControllerConfig):
    steering_range: List[float] = field(default_factory=lambda: [-1.5, 1.5])  # turning rate, rad/s


@dataclass
class QueryControllerConfig(GaussianControllerConfig):
    k_nearest: int = 10
    temperature: float = 1.0
    sigma_clip: List[float] = field(default_factory=lambda: [0.05, 1.0])


@dataclass
class SwitchingControllerConfig(ControllerConfig):
    hold_steps: Optional[int] = None  # steps each choice is held; None: one gait cycle of the run behaviour


SCHEMAS = {
    "algorithm": {"vtrace_schema": VTraceConfig, "svg0_retrace_schema": SVG0RetraceConfig,
                  "wolpertinger_schema": WolpertingerConfig},
    "controller": {"fragments_schema": FragmentsControllerConfig, "query_schema": QueryControllerConfig,
                   "steerable_schema": SteerableControllerConfig, "switching_schema": SwitchingControllerConfig,
                   "end_to_end_schema": EndToEndControllerConfig},
}


def register() -> None:
    store = ConfigStore.instance()
    for group, schemas in SCHEMAS.items():
        for name, node in schemas.items():
            store.store(group=group, name=name, node=node)


T = TypeVar("T")


def typed(schema: type[T], node: Mapping[str, Any]) -> T:
    """The schema's dataclass from a config node, typed or not (a run's saved config is plain
    YAML): its keys the schema knows, the schema's defaults for the rest."""
    return schema(**{f.name: node[f.name] for f in fields(schema) if f.name in node})
