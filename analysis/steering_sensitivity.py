"""How much a steerable run's policy and critic depend on the commanded turning rate.

    python analysis/steering_sensitivity.py outputs/<steerable stage=lowlevel run dir> [states]

On states from the run's replay, with the rate input set to +r and -r (the ends of the
training range): the policy's mean action change, the joints it changes most, and the
critic's action gradient dQ/da at both rates (how strongly, and how consistently across
states, Q asks for a rate-dependent action). A policy that changes its actions with the
rate while the body does not turn (`stage=evaluate clips=steerable`) has learned what Q
asks for, and Q asks for the wrong thing; a Q whose gradient ignores the rate gives the
policy nothing to learn from.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from hvc.agents.mlp import GaussianPolicy, QNetwork
from hvc.config import group_config


def actuator_names(body) -> list[str]:
    from dm_control import mjcf

    from hvc.envs.builders import build_walker

    physics = mjcf.Physics.from_mjcf_model(build_walker(OmegaConf.to_container(body, resolve=True)).mjcf_model)
    return [physics.model.id2name(i, "actuator") for i in range(physics.model.nu)]


def sensitivity(run_dir: Path, states: int = 2000) -> dict:
    cfg = OmegaConf.load(run_dir / "config_resolved.yaml")
    [expert] = sorted((run_dir / "experts").glob("*/checkpoint.pt"))
    state = torch.load(expert, weights_only=True)
    policy = GaussianPolicy.from_weights(state["learner"]["policy"], cfg.lowlevel.hidden, cfg.lowlevel.sigma)
    critic_weights = state["learner"]["critic"]
    action_size = policy.net[-1].out_features
    critic = QNetwork(critic_weights["normalizer.mean"].shape[0], action_size, cfg.lowlevel.critic_hidden)
    critic.load_state_dict(critic_weights)
    if "replay" not in state:
        raise SystemExit(f"{expert} holds no replay (a run packed by hvc.io.pack): resume the run for a few "
                         f"thousand env steps to refill it, then measure")
    obs = state["replay"]["obs"][:states, 0].clone()
    rate_column = policy.obs_size - 1  # the steerable policy's last input (SteerableTrackingLogic.observation)
    tracking = cfg.task if cfg.task.kind == "tracking" else group_config("task", "tracking")  # as training built it
    rate = float(max(abs(r) for r in tracking.turn_rates))

    def at(r: float) -> tuple[torch.Tensor, torch.Tensor]:
        x = obs.clone()
        x[:, rate_column] = r
        action = policy.mean(x).detach().requires_grad_(True)
        critic(x, action).sum().backward()
        return action.detach(), action.grad

    (a_left, g_left), (a_right, g_right) = at(rate), at(-rate)
    change, grad_change = a_left - a_right, g_left - g_right
    direction = torch.nn.functional.cosine_similarity(grad_change, grad_change.mean(0, keepdim=True), dim=1)
    return {"env_steps": int(state["counters"]["env_steps"]), "rate": rate,
            "action_change": change.mean(0).numpy(), "mean_abs_action_change": float(change.abs().mean()),
            "mean_abs_grad": float(g_left.abs().mean()), "mean_abs_grad_change": float(grad_change.abs().mean()),
            "grad_change_consistency": float(direction.mean()), "body": cfg.body}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="a steerable stage=lowlevel run dir with its checkpoint")
    parser.add_argument("states", type=int, nargs="?", default=2000, help="replay states to probe (default 2000)")
    args = parser.parse_args(argv)
    run_dir = args.run_dir
    result = sensitivity(run_dir, args.states)
    r = result["rate"]
    print(f"{run_dir} env_steps={result['env_steps']}")
    print(f"policy: mean |a(+{r}) - a(-{r})| = {result['mean_abs_action_change']:.3f} per action dimension")
    print(f"critic: mean |dQ/da| = {result['mean_abs_grad']:.4f}, mean |dQ/da(+{r}) - dQ/da(-{r})| = "
          f"{result['mean_abs_grad_change']:.4f}, consistency across states (mean cosine) = "
          f"{result['grad_change_consistency']:.2f}")
    names = actuator_names(result["body"])
    change = result["action_change"]
    for i in np.argsort(-np.abs(change))[:8]:
        print(f"  {names[i]:24s} a(+{r}) - a(-{r}) = {change[i]:+.3f}")


if __name__ == "__main__":
    main()
