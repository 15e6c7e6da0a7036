"""High-level training (`stage=train`, the main job) for every controller type.

Actors: `num_envs` envs (hvc.envs.vector_env; `in_process_envs` of them stepped by this
process, the rest by worker processes) each run the env, its controller and the
low-level experts; the high-level policy runs batched in this
process (central inference, as in SEED RL: on a 2-core machine one torch copy per actor
only competes for the cores). Fixed-length unrolls (Table A.1 `unroll`) with the LSTM
state at their start go into a replay buffer (Table A.1 `replay_size`, in transitions);
the learner samples unrolls, replays the LSTM from the stored state and applies V-trace
(hvc.algorithms.vtrace): value loss every step, policy gradient and entropy only where a
new high-level action was taken. Continuous controllers (steerable, end_to_end) train with
SVG(0) + Retrace (ContinuousLearner), query with a Wolpertinger-style learner
(QueryLearner). `algorithm.updates_per_unroll` paces the learner against the actors. The x-axis of the paper's curves, transitions processed by the learner, is
logged as `learner_steps`; env steps as `env_steps`.

Checkpoints (agent, optimiser, target agent, counters, RNG states, where metrics.csv stood;
not the replay, which refills): the first right after the random-policy episodes, then every
`hl.checkpoint_seconds` and on exit, so a hard kill loses at most one interval.
`resume=<run dir>` continues from the checkpoint, cutting metrics.csv back to it. A
non-finite loss stops the run before the optimiser steps, so the exit checkpoint is good.
"""
from __future__ import annotations

import json
import logging
import signal
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from hvc.agents.network import AgentSpec, HighLevelAgent, RunningNormalizer
from hvc.algorithms.hl_learners import ContinuousLearner, QueryLearner, pack_state, vtrace_update
from hvc.envs.vector_env import VectorEnv
from hvc.errors import ControllerUnavailable, HvcUserError, NonFiniteLoss
from hvc.io.checkpoint import save_checkpoint
from hvc.io.metrics import continue_metrics
from hvc.runtime.device import torch_device
from hvc.runtime.env_config import vector_env
from hvc.runtime.episodes import EpisodeRecorder
from hvc.runtime.progress import RECENT_EPISODES, Progress
from hvc.runtime.signals import raise_interrupt

log = logging.getLogger(__name__)


@dataclass
class Unrolls:
    """A ring of unrolls, batch-major numpy; images stored as uint8."""

    proprio: np.ndarray      # [U, N+1, P]
    task: np.ndarray         # [U, N+1, K]
    image: np.ndarray | None  # [U, N+1, 64, 64, 3]
    prev_reward: np.ndarray  # [U, N+1]
    prev_action: np.ndarray  # [U, N+1] int, or [U, N+1, A] for continuous controllers
    first: np.ndarray        # [U, N+1] 1 where a new episode starts (LSTM reset)
    action: np.ndarray       # [U, N] int, or [U, N, A]: the high-level action in force
    log_mu: np.ndarray       # [U, N]
    reward: np.ndarray       # [U, N]
    discount: np.ndarray     # [U, N]
    new_action: np.ndarray   # [U, N]
    state: np.ndarray        # [U, 4, H] LSTM state at the unroll's start (core h, c; policy h, c)
    query: np.ndarray | None = None  # [U, N, A] query controller: the query in force (action = selected key)
    size: int = 0
    position: int = 0

    @classmethod
    def allocate(cls, capacity: int, n: int, proprio: int, task: int, vision: bool, lstm: int, policy_lstm: int,
                 action_size: int | None = None):
        """`action_size` None: discrete actions (ints); else continuous vectors of that size."""
        hidden = max(lstm, policy_lstm)
        z = lambda *s, dt=np.float32: np.zeros(s, dt)  # noqa: E731
        act = (lambda *s: z(*s, dt=np.int64)) if action_size is None else (lambda *s: z(*s, action_size))  # noqa: E731
        return cls(z(capacity, n + 1, proprio), z(capacity, n + 1, task),
                   z(capacity, n + 1, 64, 64, 3, dt=np.uint8) if vision else None, z(capacity, n + 1),
                   act(capacity, n + 1), z(capacity, n + 1), act(capacity, n), z(capacity, n),
                   z(capacity, n), z(capacity, n), z(capacity, n), z(capacity, 4, hidden))

    @property
    def capacity(self) -> int:
        return self.proprio.shape[0]

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in vars(self).values() if isinstance(a, np.ndarray))

    def add(self, **fields) -> None:
        i = self.position
        for name, value in fields.items():
            getattr(self, name)[i] = value
        self.position = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch: int, rng: np.random.Generator, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
        """`batch` unrolls, time-major, moved to `device` once."""
        idx = rng.integers(0, self.size, batch)
        out = {}
        for name in ("proprio", "task", "image", "prev_reward", "prev_action", "first", "action", "log_mu",
                     "reward", "discount", "new_action", "query"):
            array = getattr(self, name)
            if array is not None:
                out[name] = torch.from_numpy(np.swapaxes(array[idx], 0, 1).copy()).to(device)
        out["state"] = torch.from_numpy(self.state[idx].copy()).to(device)
        return out


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
                ) -> tuple[AgentSpec, HighLevelAgent, object | None]:
    """The agent for the envs' controller on `device` and its learner (None for the discrete
    controllers, whose V-trace update is a function): what training and recording both act with."""
    agent_cfg = cfg.task.agent
    space = envs.action_space
    spec = AgentSpec(proprio_size=envs.observation_sizes["proprio"], task_size=envs.observation_sizes["task"],
                     action_size=space.n if space.discrete else space.size, discrete=space.discrete,
                     lstm_size=int(agent_cfg.lstm_size), value_mlp=tuple(agent_cfg.value_mlp),
                     vision="image" in envs.observation_sizes, critic_takes_action=not space.discrete)
    agent = HighLevelAgent(spec).to(device)
    if cfg.controller.name == "query":
        from hvc.controllers.query import QueryController

        learner = QueryLearner(agent, cfg.algorithm, cfg.controller, space,
                               QueryController(envs.skills, int(cfg.controller.k_nearest)))
        learner.rng = np.random.default_rng(int(cfg.seed))
    else:
        learner = None if space.discrete else ContinuousLearner(agent, cfg.algorithm, cfg.controller, space)
    return spec, agent, learner


def act(agent: HighLevelAgent, learner, obs: dict, prev_reward: np.ndarray, prev_action: np.ndarray,
        first: np.ndarray, lstm):
    """One batched high-level step: (what the envs get, the action, log mu, new LSTM state,
    the query or None). The envs get the selected key's fragment for `query`, the clipped
    action for the other continuous controllers (the action stays the raw sample), else the action."""
    device = agent.policy_out.weight.device
    tensor = lambda x: torch.from_numpy(x[None]).to(device)  # noqa: E731
    with torch.no_grad():
        logits, h_step, lstm = agent(
            tensor(obs["proprio"]).float(), tensor(obs["task"]).float(), tensor(prev_reward), tensor(prev_action),
            lstm, image=tensor(obs["image"]) if "image" in obs else None, done=tensor(first))
        if agent.spec.discrete:
            dist = torch.distributions.Categorical(logits=logits[0])
            action = dist.sample()
            action, log_mu = action.cpu().numpy(), dist.log_prob(action).cpu().numpy()
            return action, action, log_mu, lstm, None
        if isinstance(learner, QueryLearner):
            send, query_action, action, log_mu = learner.act(logits[0], h_step[0])
            return send, action, log_mu, lstm, query_action
        action, log_mu = learner.sample(logits[0])  # raw: replay and the agent's next input keep it
        return learner.clip(action), action, log_mu, lstm, None


def sees_clipped_actions(learner) -> bool:
    """Whether the agent's next input is the clipped action the env got while replay keeps the
    raw sample (SVG(0) controllers; the query's input is its selected key)."""
    return isinstance(learner, ContinuousLearner) and not isinstance(learner, QueryLearner)


def carry(action: np.ndarray, prev_action: np.ndarray, rewards: np.ndarray, dones: np.ndarray, infos,
          seen: np.ndarray | None = None):
    """After a step: (new-action flags, the action in force: the new one only where the
    controller took it, then the previous reward, previous action and episode-start flags
    the agent sees next, zeroed where an episode ended). `seen` is what the agent sees of a
    new action if not the action itself (a raw continuous sample's clipped value, what the env got)."""
    new = np.array([float(i.get("new_action", False)) for i in infos], np.float32)
    held = new.reshape(-1, *([1] * (action.ndim - 1))) > 0
    in_force = np.where(held, action, prev_action)
    next_action = np.where(held, action if seen is None else seen, prev_action)
    next_reward = rewards.astype(np.float32)
    next_action[dones], next_reward[dones] = 0, 0.0
    return new, in_force, next_reward, next_action, dones.astype(np.float32)


def learning_discounts(discounts: np.ndarray, dones: np.ndarray) -> np.ndarray:
    """The discounts the learner sees: 0 wherever an episode ended, time limits included.
    The actors reset at once, so the next stored step is a new episode's first: a time
    limit's env discount of 1 would bootstrap from that state and carry V-trace and
    Retrace traces across the boundary (IMPALA also treats truncation as termination)."""
    return np.where(dones, 0.0, discounts).astype(np.float32)


def run_hl_training(cfg: DictConfig, run_dir: Path) -> dict:
    # acting (a few frames per call) runs on one thread; only the learner's batched updates take
    # `torch_threads`: the worker envs wait for them, while threads of small calls only contend
    torch.set_num_threads(1)
    learner_threads = int(cfg.torch_threads)
    hl, agent_cfg = cfg.hl, cfg.task.agent
    rng = np.random.default_rng(cfg.seed)
    torch.manual_seed(cfg.seed)
    checkpoint = run_dir / "checkpoint.pt"
    state = load_checkpoint(checkpoint) if checkpoint.exists() else None
    resumed_at = int(state["counters"]["env_steps"]) if state else 0
    if state is None and cfg.get("resume"):
        log.warning("%s has no checkpoint (killed before its first one): starting it from env step 0, "
                    "its metrics rewritten", run_dir)
    if resumed_at >= int(cfg.total_steps):
        log.warning("%s is complete: %d env steps done of total_steps=%d; pass a larger total_steps= to go on",
                    run_dir, resumed_at, int(cfg.total_steps))
        return {"env_steps": resumed_at, "learner_steps": int(state["counters"]["updates"]) * int(
            cfg.algorithm.batch_size) * int(cfg.task.agent.unroll), "episodes": int(state["counters"]["episodes"])}
    envs = make_envs(cfg, seed=int(cfg.seed) + resumed_at)  # resumed: new episodes, not the first ones again
    device = torch_device(cfg.get("device", "cpu"))
    spec, agent, learner = build_agent(cfg, envs, device)
    vision = spec.vision
    discrete = spec.discrete
    query = isinstance(learner, QueryLearner)
    clipped_actions = sees_clipped_actions(learner)
    optimizer = torch.optim.Adam(agent.parameters(),
                                 lr=float(cfg.algorithm.learning_rate))
    n, batch = int(agent_cfg.unroll), int(cfg.algorithm.batch_size)
    capacity = max(batch, int(agent_cfg.replay_size) // n)
    hidden = max(spec.lstm_size, spec.policy_lstm)
    replay = Unrolls.allocate(capacity, n, spec.proprio_size, spec.task_size, vision, spec.lstm_size,
                              spec.policy_lstm, None if discrete else spec.action_size)
    if query:
        replay.query = np.zeros_like(replay.action)
    log.info("replay: %d unrolls of %d steps, %.2f GiB", replay.capacity, n, replay.nbytes / 2 ** 30)
    prev_query = np.zeros((cfg.num_envs, spec.action_size), np.float32) if query else None
    counters = {"env_steps": 0, "updates": 0, "episodes": 0}
    update_credit = 0.0  # learner updates owed to the actors (algorithm.updates_per_unroll may be fractional)
    if state is not None:
        agent.load_state_dict(state["agent"])
        optimizer.load_state_dict(state["optimizer"])
        for group in optimizer.param_groups:  # the configured rate, not the one saved with the optimiser
            group["lr"] = float(cfg.algorithm.learning_rate)
        counters = {k: int(v) for k, v in state["counters"].items()}
        update_credit = float(state.get("update_credit", 0.0))
        if learner is not None:
            learner.target.load_state_dict(state["target_agent"])
            learner.steps = counters["updates"]  # keeps the target refresh schedule
        rng.bit_generator.state = json.loads(state["rng"])
        torch.set_rng_state(state["torch_rng"])
        if device.type == "cuda" and "cuda_rng" in state:
            torch.cuda.set_rng_state(state["cuda_rng"], device)
        if query:
            learner.rng = np.random.default_rng([int(cfg.seed), resumed_at])
        log.info("resumed from %s at env step %d (replay refills)", checkpoint, counters["env_steps"])

    def save() -> None:
        save_checkpoint({"agent": agent.state_dict(), "optimizer": optimizer.state_dict(), "counters": counters,
                    "spec": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(spec).items()},
                    **({"target_agent": learner.target.state_dict()} if learner is not None else {}),
                    "rng": json.dumps(rng.bit_generator.state),
                    "torch_rng": torch.get_rng_state(), "update_credit": update_credit,
                    **({"cuda_rng": torch.cuda.get_rng_state(device)} if device.type == "cuda" else {}),
                    "metrics": metrics.mark()}, checkpoint)

    gamma, entropy_cost = float(agent_cfg.gamma), float(cfg.algorithm.get("entropy_cost", 0.01))
    recorder = EpisodeRecorder.for_run(cfg, run_dir)
    metrics, dropped = continue_metrics(run_dir / "metrics.csv", state, tensorboard=True)
    if dropped:
        log.info("metrics.csv: dropped %d rows logged after the checkpoint's env step %d", dropped,
                 resumed_at if state else -1)
    E = envs.num_envs
    obs = envs.reset()
    lstm = agent.initial_state(E)
    prev_reward, first = np.zeros(E, np.float32), np.ones(E, np.float32)
    prev_action = np.zeros(E, np.int64) if discrete else np.zeros((E, spec.action_size), np.float32)
    returns: list[float] = []  # since the last metrics row
    recent = deque(maxlen=RECENT_EPISODES)  # what progress shows
    losses: dict[str, float] = {}
    updates_per_unroll = float(cfg.algorithm.updates_per_unroll)
    start, last_save, last_log = time.perf_counter(), time.monotonic(), counters["env_steps"]
    start_steps = counters["env_steps"]  # a resumed run's rate counts only its own steps
    progress = Progress("hl train", int(cfg.total_steps), counters["env_steps"], float(cfg.progress_seconds))
    previous_sigterm = signal.signal(signal.SIGTERM, raise_interrupt)  # `kill` saves a checkpoint too
    try:
        with progress.closing():
            if counters["env_steps"] == 0:
                if int(hl.random_episodes) > 0:
                    random_returns = _random_baseline(envs, int(hl.random_episodes), rng)
                    metrics.log(0, {"random_return": float(np.mean(random_returns))})
                    obs = envs.reset()
                save()  # the first checkpoint: a kill from here on loses at most one interval
            while counters["env_steps"] < int(cfg.total_steps):
                seq = {k: [] for k in ("proprio", "task", "image", "prev_reward", "prev_action", "first", "action",
                                       "log_mu", "reward", "discount", "new_action", "query")}
                start_state = pack_state(lstm, hidden)
                for _ in range(n):
                    seq["proprio"].append(obs["proprio"])
                    seq["task"].append(obs["task"])
                    if vision:
                        seq["image"].append(obs["image"])
                    seq["prev_reward"].append(prev_reward.copy())
                    seq["prev_action"].append(prev_action.copy())
                    seq["first"].append(first.copy())
                    agent.normalizer.update(torch.from_numpy(np.concatenate([obs["proprio"], obs["task"]], -1)).to(device))
                    send, action, log_mu, lstm, query_action = act(agent, learner, obs, prev_reward, prev_action,
                                                                   first, lstm)
                    before = {k: v[0] for k, v in obs.items()}
                    obs, rewards, discounts, dones, infos = envs.step(send)
                    new, in_force, prev_reward, next_action, first = carry(action, prev_action, rewards, dones, infos,
                                                                           seen=send if clipped_actions else None)
                    if query:
                        prev_query = np.where(new[:, None] > 0, query_action, prev_query)
                        seq["query"].append(prev_query.copy())
                    recorder.add(before, float(rewards[0]), infos[0], bool(dones[0]),
                                 query=prev_query[0] if query else None)
                    seq["action"].append(in_force)
                    seq["log_mu"].append(log_mu)
                    seq["reward"].append(rewards)
                    seq["discount"].append(learning_discounts(discounts, dones))
                    seq["new_action"].append(new)
                    prev_action = next_action
                    for info in infos:
                        if "episode_return" in info:
                            returns.append(info["episode_return"])
                            recent.append(info["episode_return"])
                            counters["episodes"] += 1
                    counters["env_steps"] += E
                # the step after the unroll, for bootstrapping
                tail = {"proprio": obs["proprio"], "task": obs["task"], "prev_reward": prev_reward,
                        "prev_action": prev_action, "first": first}
                for e in range(E):
                    fields = {k: np.stack([s[e] for s in seq[k]] + ([tail[k][e]] if k in tail else []))
                              for k in ("proprio", "task", "prev_reward", "prev_action", "first")}
                    if vision:
                        fields["image"] = np.stack([s[e] for s in seq["image"]] + [obs["image"][e]])
                    fields.update({k: np.stack([s[e] for s in seq[k]]) for k in
                                   ("action", "log_mu", "reward", "discount", "new_action") + (("query",) if query else ())})
                    replay.add(state=start_state[e], **fields)
                if replay.size >= int(hl.min_replay_unrolls):
                    update_credit += updates_per_unroll * E  # per unroll added; fractions accumulate
                    torch.set_num_threads(learner_threads)
                    while update_credit >= 1.0:
                        update_credit -= 1.0
                        sample = replay.sample(batch, rng, device)
                        try:
                            losses = (vtrace_update(agent, optimizer, sample, gamma, entropy_cost, cfg.algorithm)
                                      if discrete else learner.update(optimizer, sample, gamma))
                        except NonFiniteLoss as error:  # raised before the step: the state saved below is good
                            raise NonFiniteLoss(f"{error} at env step {counters['env_steps']}; the last good state "
                                                f"is saved in {checkpoint}") from None
                        counters["updates"] += 1
                    torch.set_num_threads(1)
                if counters["env_steps"] - last_log >= int(cfg.log_every):
                    last_log = counters["env_steps"]
                    row = {"episodes": counters["episodes"],
                           "steps_per_second": (counters["env_steps"] - start_steps) / (time.perf_counter() - start)}
                    if returns:
                        row["episode_return"] = float(np.mean(returns))
                        returns = []
                    if losses:
                        row.update(losses)  # the latest update's
                    metrics.log(counters["env_steps"], row, learner_steps=counters["updates"] * batch * n)
                progress.update(counters["env_steps"], float(np.mean(recent)) if recent else None,
                                counters["updates"] * batch * n)
                if time.monotonic() - last_save > float(hl.checkpoint_seconds):
                    save()
                    last_save = time.monotonic()
    finally:
        signal.signal(signal.SIGTERM, previous_sigterm)
        try:
            save()
        finally:
            metrics.close()
            envs.close()
    return {"env_steps": counters["env_steps"], "learner_steps": counters["updates"] * batch * n,
            "episodes": counters["episodes"]}


def _random_baseline(envs: VectorEnv, episodes: int, rng: np.random.Generator) -> list[float]:
    """Returns of uniformly random high-level actions: the bar a learning curve must clear."""
    envs.reset()
    out: list[float] = []
    while len(out) < episodes:
        _, _, _, _, infos = envs.step(envs.random_actions(rng))
        out += [i["episode_return"] for i in infos if "episode_return" in i]
    return out[:episodes]
