"""High-level training (`stage=train`, the main job) for every controller type.

Actors: `num_envs` envs (hvc.envs.vector_env; `in_process_envs` of them stepped by this
process, the rest by worker processes) each run the env, its controller and the
low-level experts; the high-level policy acts batched in this process (hvc.runtime.acting).
With `actors=ray ray.acting=actors`, Ray actors act on their own and send whole unrolls
(hvc.runtime.ray_acting); the loop below takes unrolls from either alike.
Fixed-length unrolls (Table A.1 `unroll`) with the LSTM state at their start go into a
replay buffer (Table A.1 `replay_size`, in transitions); the learner (the `algorithm`
config's class: V-trace for the discrete controllers, SVG(0) + Retrace for the continuous
ones, Wolpertinger for query; hvc.algorithms) samples unrolls and replays the LSTM from the
stored state. `algorithm.updates_per_unroll` paces the learner against the actors (Pacer).
The x-axis of the paper's curves, transitions processed by the learner, is logged as
`learner_steps`; env steps as `env_steps`.

Checkpoints (the learner's state: agent, optimiser, target agent; counters, RNG states,
where metrics.csv stood; not the replay, which refills): the first right after the
random-policy episodes, then every `hl.checkpoint_seconds` and on exit, so a hard kill loses
at most one interval. `resume=<run dir>` continues from the checkpoint, cutting metrics.csv
back to it. A non-finite loss stops the run before the optimiser steps, so the exit
checkpoint is good.
"""
from __future__ import annotations

import logging
import signal
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch
from hydra.utils import get_class
from omegaconf import DictConfig

from hvc.agents.network import AgentSpec, HighLevelAgent, RunningNormalizer
from hvc.algorithms.learner import Learner, Pacer
from hvc.algorithms.replay import Field, UnrollReplay
from hvc.envs.vector_env import VectorEnv
from hvc.errors import ControllerUnavailable, HvcUserError, NonFiniteLoss
from hvc.io.checkpoint import random_states, restore_random_states, save_checkpoint
from hvc.io.metrics import continue_metrics
from hvc.runtime.acting import Actor, LocalActing
from hvc.runtime.device import torch_device
from hvc.runtime.env_config import vector_env
from hvc.runtime.episodes import EpisodeRecorder
from hvc.runtime.progress import RECENT_EPISODES, Progress
from hvc.runtime.signals import raise_interrupt

log = logging.getLogger(__name__)


def unroll_fields(spec: AgentSpec, n: int, query: bool = False) -> dict[str, Field]:
    """What replay keeps of one high-level unroll of `n` steps: the agent's inputs at n + 1
    steps (the last for bootstrapping), images as uint8; per step the action in force (an int,
    or a vector for continuous controllers), its log mu, reward, discount and new-action flag;
    for the query controller the query in force (its action is the selected key); and the LSTM
    state at the unroll's start (core h, c; policy h, c)."""
    action = Field((n,), np.int64) if spec.discrete else Field((n, spec.action_size))
    fields = {"proprio": Field((n + 1, spec.proprio_size)), "task": Field((n + 1, spec.task_size)),
              "prev_reward": Field((n + 1,)), "first": Field((n + 1,)),
              "prev_action": Field((n + 1, *action.shape[1:]), action.dtype), "action": action,
              **{k: Field((n,)) for k in ("log_mu", "reward", "discount", "new_action")},
              "state": Field((4, max(spec.lstm_size, spec.policy_lstm)), per_step=False)}
    if spec.vision:
        fields["image"] = Field((n + 1, *spec.image_size, 3), np.uint8)
    if query:
        fields["query"] = Field((n, spec.action_size))
    return fields


def make_envs(cfg: DictConfig, seed: int | None = None) -> VectorEnv:
    """`cfg.num_envs` actors of the task with the configured controller and its experts,
    seeded `seed` (default cfg.seed), seed + 1, ..."""
    envs = vector_env(cfg, seed)
    if envs.controller is None:
        envs.close()
        raise ControllerUnavailable(f"controller={cfg.controller.name} could not be built: {envs.why_no_controller}")
    return envs


def load_checkpoint(path: Path) -> dict:
    """A stage=train checkpoint, refusing one from before input normalisation in one line."""
    state = torch.load(path, weights_only=True, map_location="cpu")  # a GPU run records and resumes anywhere
    if "normalizer.mean" not in state["agent"]:
        raise HvcUserError(f"{path} was written by an older hvc (before input normalisation and the "
                           f"sigmoid-bounded sigma) and cannot be used; start a new run")
    if "normalizer.var_floor" not in state["agent"]:
        log.warning("%s does not record its input normaliser's variance floor; assuming %g (hvc since "
                    "2026-12-01 20:17; 1e-6 before)", path, RunningNormalizer.DEFAULT_VAR_FLOOR)
    return state


def build_agent(cfg: DictConfig, envs: VectorEnv, device: torch.device | str = "cpu"
                ) -> tuple[AgentSpec, HighLevelAgent, Learner]:
    """The agent for the envs' controller on `device` and its learner (the class the `algorithm`
    config's `_target_` names): what training and recording both act with."""
    agent_cfg = cfg.task.agent
    space = envs.action_space
    image = envs.observation_sizes.get("image")
    spec = AgentSpec(proprio_size=envs.observation_sizes["proprio"], task_size=envs.observation_sizes["task"],
                     action_size=space.n if space.discrete else space.size, discrete=space.discrete,
                     lstm_size=int(agent_cfg.lstm_size), value_mlp=tuple(agent_cfg.value_mlp),
                     vision=image is not None, critic_takes_action=not space.discrete,
                     image_precision=str(cfg.image_precision), image_size=tuple(image[:2]) if image else (64, 64))
    agent = HighLevelAgent(spec).to(device)
    learner_class = get_class(cfg.algorithm._target_)
    controller = None
    if learner_class.uses_controller:  # e.g. Wolpertinger's keys: the controller the envs run, built here too
        from hvc.controllers.factory import build_controller

        controller = build_controller(cfg.controller, None, envs.skills)
    return spec, agent, learner_class.from_config(agent, cfg, space, controller)


def run_hl_training(cfg: DictConfig, run_dir: Path) -> dict:
    # acting (a few frames per call) runs on one thread; only the learner's batched updates take
    # `torch_threads`: the worker envs wait for them, while threads of small calls only contend
    torch.set_num_threads(1)
    learner_threads = int(cfg.torch_threads)
    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    checkpoint = run_dir / "checkpoint.pt"
    state = load_checkpoint(checkpoint) if checkpoint.exists() else None
    resumed_at = int(state["counters"]["env_steps"]) if state else 0
    n, batch = int(cfg.task.agent.unroll), int(cfg.algorithm.batch_size)
    if state is None and cfg.get("resume"):
        log.warning("%s has no checkpoint (killed before its first one): starting it from env step 0, "
                    "its metrics rewritten", run_dir)
    if resumed_at >= int(cfg.total_steps):
        log.warning("%s is complete: %d env steps done of total_steps=%d; pass a larger total_steps= to go on",
                    run_dir, resumed_at, int(cfg.total_steps))
        return {"env_steps": resumed_at, "learner_steps": int(state["counters"]["updates"]) * batch * n,
                "episodes": int(state["counters"]["episodes"])}
    seed = int(cfg.seed) + resumed_at  # resumed: new episodes, not the first ones again
    device = torch_device(cfg.get("device", "cpu"))
    in_actors = cfg.get("actors", "local") == "ray" and cfg.ray.get("acting", "central") == "actors"
    if in_actors:  # Ray actors run whole unrolls with their own copy of the agent (hvc.runtime.ray_acting)
        from hvc.runtime.ray_acting import RayActing

        envs = RayActing(cfg, seed, run_dir)
        if envs.controller is None:
            envs.close()
            raise ControllerUnavailable(f"controller={cfg.controller.name} could not be built: "
                                        f"{envs.why_no_controller}")
    else:
        envs = make_envs(cfg, seed=seed)
    spec, agent, learner = build_agent(cfg, envs, device)
    replay = UnrollReplay(max(batch, int(cfg.task.agent.replay_size) // n),
                          unroll_fields(spec, n, query=learner.keeps_query))
    log.info("replay: %d unrolls of %d steps, %.2f GiB", replay.capacity, n, replay.nbytes / 2 ** 30)
    counters = {"env_steps": 0, "updates": 0, "episodes": 0}
    pacer = Pacer(cfg.algorithm.updates_per_unroll)
    if state is not None:
        learner.load_state_dict(state)
        counters = {k: int(v) for k, v in state["counters"].items()}
        pacer.credit = float(state.get("update_credit", 0.0))
        restore_random_states(state, {"rng": rng}, device)
        log.info("resumed from %s at env step %d (replay refills)", checkpoint, counters["env_steps"])

    def save() -> None:
        save_checkpoint({**learner.state_dict(), "counters": counters,
                         "spec": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(spec).items()},
                         **random_states({"rng": rng}, device), "update_credit": pacer.credit,
                         "metrics": metrics.mark()}, checkpoint)

    metrics, dropped = continue_metrics(run_dir / "metrics.csv", state, tensorboard=True)
    if dropped:
        log.info("metrics.csv: dropped %d rows logged after the checkpoint's env step %d", dropped,
                 resumed_at if state else -1)
    if in_actors:
        acting = envs.attach(agent)
    else:
        acting = LocalActing(Actor(agent, learner, envs, EpisodeRecorder.for_run(cfg, run_dir, envs.skills)), n,
                             replay.fields)
    returns: list[float] = []  # since the last metrics row
    recent = deque(maxlen=RECENT_EPISODES)  # what progress shows
    losses: dict[str, float] = {}
    start, last_save, last_log = time.perf_counter(), time.monotonic(), counters["env_steps"]
    start_steps = counters["env_steps"]  # a resumed run's rate counts only its own steps
    progress = Progress("hl train", int(cfg.total_steps), counters["env_steps"], float(cfg.progress_seconds))
    previous_sigterm = signal.signal(signal.SIGTERM, raise_interrupt)  # `kill` saves a checkpoint too
    try:
        with progress.closing():
            if state is None:  # a resume from the first checkpoint (step 0) has logged these already
                if int(cfg.hl.random_episodes) > 0:
                    random_returns = acting.random_returns(int(cfg.hl.random_episodes), rng)
                    metrics.log(0, {"random_return": float(np.mean(random_returns))})
                save()  # the first checkpoint: a kill from here on loses at most one interval
            acting.publish(counters["updates"])
            while counters["env_steps"] < int(cfg.total_steps):
                collected = acting.collect()
                for unroll in collected.unrolls:
                    replay.add(**unroll)
                returns += collected.returns
                recent.extend(collected.returns)
                counters["episodes"] += len(collected.returns)
                counters["env_steps"] += collected.env_steps
                if replay.size >= int(cfg.hl.min_replay_unrolls):
                    torch.set_num_threads(learner_threads)
                    for _ in range(pacer.owed(len(collected.unrolls))):
                        try:
                            losses = learner.update(replay.sample(batch, rng, device))
                        except NonFiniteLoss as error:  # raised before the step: the state saved below is good
                            raise NonFiniteLoss(f"{error} at env step {counters['env_steps']}; the last good state "
                                                f"is saved in {checkpoint}") from None
                        counters["updates"] += 1
                    torch.set_num_threads(1)
                    acting.publish(counters["updates"])
                if counters["env_steps"] - last_log >= int(cfg.log_every):
                    last_log = counters["env_steps"]
                    row = {"episodes": counters["episodes"],
                           "steps_per_second": (counters["env_steps"] - start_steps) / (time.perf_counter() - start)}
                    if returns:
                        row["episode_return"] = float(np.mean(returns))
                        returns = []
                    row.update(losses)  # the latest update's
                    metrics.log(counters["env_steps"], row, learner_steps=counters["updates"] * batch * n)
                progress.update(counters["env_steps"], float(np.mean(recent)) if recent else None,
                                counters["updates"] * batch * n)
                if time.monotonic() - last_save > float(cfg.hl.checkpoint_seconds):
                    save()
                    last_save = time.monotonic()
    finally:
        signal.signal(signal.SIGTERM, previous_sigterm)
        try:
            save()
        finally:
            metrics.close()
            acting.close()
    return {"env_steps": counters["env_steps"], "learner_steps": counters["updates"] * batch * n,
            "episodes": counters["episodes"]}

