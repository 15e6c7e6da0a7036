"""Training one time-indexed tracking expert pi(a | s, t) for one clip (Sec. 2.1).

1. Supervised pre-training on the reference: max log pi(q*_{t+1} | s*_t, t), i.e. with the
   fixed sigma a regression of the action on the next reference pose, from the states
   of the reference itself (poor control alone, but it shortens RL considerably).
2. Off-policy RL on the tracking reward: the actor (numpy copy of the policy, fixed
   noise sigma = 0.1) writes unrolls to a replay buffer from random starts along the
   clip; the learner does SVG(0) + Retrace updates (hvc.algorithms.svg0_retrace). A
   switching policy may keep its teachers through RL (`kickstart_cost`, kickstarting).

Everything needed to continue lives in `checkpoint.pt` (weights, optimisers, replay,
counters, RNG states; loadable with torch.load(weights_only=True)), written atomically
every `checkpoint_seconds` and at the end; a run restarted on the same directory
resumes (without the replay when it was packed to move machines: it refills). A
non-finite loss stops the run with a clear message, keeping the last good checkpoint.
"""
from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path
from typing import Mapping

import mujoco
import numpy as np
import torch
from torch import nn

from hvc.agents.mlp import GaussianPolicy, NumpyPolicy, QNetwork
from hvc.algorithms.replay import UnrollReplay, pad_unroll, svg0_fields
from hvc.algorithms.learner import Pacer
from hvc.algorithms.svg0_retrace import Batch, SVG0Retrace
from hvc.envs.fast_env import FastEnv
from hvc.errors import NonFiniteLoss
from hvc.io.checkpoint import random_states, restore_random_states, save_checkpoint, write_atomically
from hvc.io.metrics import continue_metrics
from hvc.lowlevel.evaluation import evaluate
from hvc.lowlevel.library import policy_observation
from hvc.lowlevel.pushes import Pushes
from hvc.lowlevel.switch_starts import cut_in, switch_library, switch_starts, switch_states_for


def reference_dataset(env: FastEnv, walks: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """(observations of the reference states s*_t, actions reaching q*_{t+1}), t < T-1, over
    `walks` references when each episode draws its own (steered cycles, Markov walks)."""
    logic = env.layout.logic
    obs, actions = [], []
    for _ in range(walks if logic.reference_per_episode else 1):
        env.reset()
        ref = logic.reference
        for t in range(ref.num_steps - 1):
            logic.set_reference_state(env.data, t)
            mujoco.mj_forward(env.model, env.data)
            logic.t = t
            obs.append(policy_observation(env.observation()))
            actions.append(np.clip(logic.pose_to_actuation(ref.joints[t + 1]), -1, 1))
    return np.asarray(obs, np.float32), np.asarray(actions, np.float32)


def perturbed_dataset(env: FastEnv, episodes: int, sigma: float,
                      rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """States visited by playing the reference's next pose with the policy's noise from
    random starts, each labelled with the reference's next pose at its time index: the
    pre-trained policy then sees the states it will meet, not only the reference's."""
    logic = env.layout.logic
    obs_list, actions = [], []
    for _ in range(episodes):
        obs, done = env.reset(), False
        ref = logic.reference  # the reset may have drawn a new one
        while not done:
            target = np.clip(logic.pose_to_actuation(ref.joints[min(logic.t + 1, ref.num_steps - 1)]), -1, 1)
            obs_list.append(policy_observation(obs))
            actions.append(target)
            obs, _, _, done = env.step(target + sigma * rng.standard_normal(target.shape))
    return np.asarray(obs_list, np.float32), np.asarray(actions, np.float32)


def distillation_dataset(env: FastEnv, experts: list[NumpyPolicy], episodes: int, sigma: float,
                         rng: np.random.Generator, until_switch: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """States of Markov walks driven, with the policy's noise, by the expert of the behaviour
    in force, each labelled with that expert's action (the expert sees proprioception and its
    own phase, a prefix of the switching policy's input): regressing on them starts the
    switching policy as good as the experts are within behaviours, and cold-switching at
    the walks' cuts, instead of from the reference's open-loop poses. `until_switch` ends
    each walk at its first cut: only states where the expert tracks its own clip."""
    logic = env.layout.logic
    obs_list, actions = [], []
    for _ in range(episodes):
        obs, done = env.reset(), False
        first = int(logic.labels[logic.t])
        while not done and not (until_switch and int(logic.labels[logic.t]) != first):
            x = policy_observation(obs)
            expert = experts[int(logic.labels[logic.t])]
            target = expert(x[:expert.weights[0].shape[0]])
            obs_list.append(x)
            actions.append(target)
            obs, _, _, done = env.step(target + sigma * rng.standard_normal(target.shape))
    return np.asarray(obs_list, np.float32), np.asarray(actions, np.float32)


def pretrain(policy: GaussianPolicy, obs: np.ndarray, actions: np.ndarray, steps: int, lr: float,
             batch: int, rng: np.random.Generator) -> tuple[float, float]:
    """Behaviour cloning of the next reference pose; returns the action MSE before and after."""
    opt = torch.optim.Adam(policy.net.parameters(), lr=lr)
    x, y = torch.from_numpy(obs), torch.from_numpy(actions)

    def mse() -> float:
        with torch.no_grad():
            return float(((policy.mean(x) - y) ** 2).mean())

    before = mse()
    for _ in range(steps):
        xb, yb = _sample((x, y), batch, rng)
        loss = ((policy.mean(xb) - yb) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return before, mse()


def load_warm_start(policy: GaussianPolicy, expert: NumpyPolicy, mean: np.ndarray, std: np.ndarray) -> None:
    """Sets `policy` to act as `expert`, a trained policy of the same clip whose observation
    is a prefix of this one's (proprioception and phase; the steerable policy adds its turning
    rate): the extra inputs get zero weights and normalisation from (mean, std), so the new
    policy starts by ignoring them and tracks as well as the expert did."""
    linears = [m for m in policy.net if isinstance(m, nn.Linear)]
    shapes = [tuple(m.weight.shape[::-1]) for m in linears]
    known = expert.weights[0].shape[0]
    if (len(expert.weights) != len(linears) or [w.shape for w in expert.weights[1:]] != shapes[1:]
            or expert.weights[0].shape[1] != shapes[0][1] or known > shapes[0][0]):
        raise ValueError(f"cannot warm-start a policy of layer shapes {shapes} from an expert of layer shapes "
                         f"{[w.shape for w in expert.weights]}: set lowlevel.hidden to the expert's")
    with torch.no_grad():
        for i, (m, w, b) in enumerate(zip(linears, expert.weights, expert.biases)):
            m.weight.zero_()
            m.weight[:, :w.shape[0]] = torch.from_numpy(w.T)
            m.bias.copy_(torch.from_numpy(b))
    mean, std = np.array(mean, np.float32), np.array(std, np.float32)
    mean[:known], std[:known] = expert.mean_obs, 1.0 / expert.inv_std
    policy.normalizer.set(mean, std)


class StopRequest:
    """SIGTERM (the launcher stopping its workers, or `kill`) asks the training loop to save a
    checkpoint and stop at the next unroll boundary, instead of losing what it did since the
    last periodic checkpoint (up to `checkpoint_seconds`)."""

    def __init__(self):
        self.requested = False
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, self._request)

    def _request(self, signum, frame) -> None:
        self.requested = True


def train_expert(task: Mapping, body: Mapping, render: Mapping, cfg: Mapping, out_dir: Path,
                 total_steps: int, seed: int = 0, parent_pid: int | None = None,
                 warm_start: NumpyPolicy | list[NumpyPolicy] | None = None) -> dict[str, float]:
    """Trains (or resumes) one expert in `out_dir`; returns its final evaluation. With
    `parent_pid`, stops after a checkpoint if that process dies (no orphaned workers).
    A fresh run with `warm_start` starts from that policy (load_warm_start), or distils a
    list of per-behaviour experts (distillation_dataset), instead of behaviour cloning, and
    trains only its new critic for `warm_start_critic_steps` learner steps, since SVG(0)
    through an untrained Q would undo what the policy knows."""
    torch.set_num_threads(1)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    cut_rng = np.random.default_rng([seed, 29])  # cut-ins' own stream: without them, runs draw as before
    push_rng = np.random.default_rng([seed, 31])  # the pushes' own, likewise
    torch.manual_seed(seed)
    env = FastEnv.build(task, body, render, seed=seed, render=False)
    streams = {"rng": rng, "env_rng": env.rng, "cut_rng": cut_rng, "push_rng": push_rng}
    logic = env.layout.logic
    obs_size = env.layout.proprio.size + logic.observation_size
    privileged = bool(cfg.get("critic_sees_reference", False))
    state_size = obs_size + (logic.critic_feature_size if privileged else 0)

    def stored(obs: dict) -> np.ndarray:
        """What replay keeps: the policy's observation, then (privileged) the critic's extras."""
        x = policy_observation(obs)
        return np.concatenate([x, logic.critic_features(env.data)]) if privileged else x

    sigma = float(cfg["sigma"])
    policy = GaussianPolicy(obs_size, env.action_size, cfg["hidden"], sigma)  # reads the first obs_size columns
    critic = QNetwork(state_size, env.action_size, cfg["critic_hidden"])
    learner = SVG0Retrace(policy, critic, cfg)
    replay = UnrollReplay(int(cfg["replay_unrolls"]), svg0_fields(int(cfg["unroll"]), state_size, env.action_size))
    checkpoint = out_dir / "checkpoint.pt"
    counters = {"env_steps": 0, "episodes": 0, "critic_only_until": 0}
    state = torch.load(checkpoint, weights_only=True) if checkpoint.exists() else None
    teacher = None
    if float(cfg.get("kickstart_cost", 0.0)) > 0:  # the same walks on resume: drawn from the env's freshly seeded
        if not isinstance(warm_start, list):     # stream, which then goes back, so the run draws as without them
            raise ValueError("kickstart_cost needs warm_start: a list of one expert per behaviour (the teachers)")
        fresh = env.rng.bit_generator.state
        teacher = tuple(torch.from_numpy(a) for a in distillation_dataset(
            env, list(warm_start), int(cfg["bc_rollouts"]), sigma, np.random.default_rng([seed, 37]),
            until_switch=True))
        env.rng.bit_generator.state = fresh
    metrics, _ = continue_metrics(out_dir / "metrics.csv", state, tensorboard=True)  # no row twice after a kill
    if state is not None:
        learner.load_state_dict(state["learner"])
        if "replay" in state:  # not in a packed run (hvc.io.pack): the replay refills
            replay.load_state_dict(state["replay"])
        counters.update({k: int(v) for k, v in state["counters"].items()})
        restore_random_states(state, {k: g for k, g in streams.items() if k in state})  # older: no cut_rng, push_rng
    elif warm_start is not None:
        if isinstance(warm_start, NumpyPolicy):
            ref_obs, _ = reference_dataset(env)
            load_warm_start(policy, warm_start, ref_obs.mean(0), ref_obs.std(0))
        else:  # one expert per behaviour of the switching policy
            obs, actions = distillation_dataset(env, list(warm_start), int(cfg["bc_rollouts"]), sigma, rng)
            policy.normalizer.set(obs.mean(0), obs.std(0))
            before, after = pretrain(policy, obs, actions, int(cfg["distill_steps"]), float(cfg["bc_lr"]),
                                     int(cfg["bc_batch"]), rng)
            metrics.log(0, {"distill_mse_before": before, "distill_mse_after": after})
        _critic_normalizer(critic, policy)
        learner.sync_targets()
        counters["critic_only_until"] = int(cfg.get("warm_start_critic_steps", 0))
        metrics.log(0, evaluate(env, _greedy(NumpyPolicy.from_torch(policy)), int(cfg["eval_episodes"]), "eval_"))
    else:
        ref_obs, ref_actions = reference_dataset(env)
        near_obs, near_actions = perturbed_dataset(env, int(cfg["bc_rollouts"]), sigma, rng)
        ref_obs, ref_actions = np.concatenate([ref_obs, near_obs]), np.concatenate([ref_actions, near_actions])
        mean, std = ref_obs.mean(0), ref_obs.std(0)
        policy.normalizer.set(mean, std)
        _critic_normalizer(critic, policy)
        before, after = pretrain(policy, ref_obs, ref_actions, int(cfg["bc_steps"]), float(cfg["bc_lr"]),
                                 int(cfg["bc_batch"]), rng)
        learner.sync_targets()
        metrics.log(0, {"bc_mse_before": before, "bc_mse_after": after})
        metrics.log(0, evaluate(env, _greedy(NumpyPolicy.from_torch(policy)), int(cfg["eval_episodes"]), "eval_"))

    def save() -> None:
        save_checkpoint({"learner": learner.state_dict(), "replay": replay.state_dict(), "counters": counters,
                         **random_states(streams), "metrics": metrics.mark()}, checkpoint)

    if state is None:
        save()  # behaviour cloning done: a kill from here on loses at most one interval

    switching, cutting = float(cfg.get("switch_starts", 0.0)), float(cfg.get("cut_ins", 0.0))
    fragment_len = int(cfg.get("switch_fragment_len", 3))
    cutters = None
    if switching > 0 or cutting > 0:  # after pre-training, which learns from the reference's own states
        library = switch_library(cfg)
        states = switch_states_for(env, library.experts, cfg, seed)  # scored from at the end either way
        for layout in env.layouts:
            layout.logic.switch_states, layout.logic.switch_probability = states, switching
        cutters = library.experts if cutting > 0 else None
    pushes = None
    if float(cfg.get("pushes", 0.0)) > 0:
        pushes = Pushes(float(cfg["pushes"]), float(cfg["push_force"]), int(cfg["push_steps"]), logic.root, push_rng,
                        fall_window=int(round(1.0 / env.control_timestep)))
    actor = NumpyPolicy.from_torch(policy)
    pacer = Pacer(cfg["updates_per_unroll"])
    unroll, batch_size = int(cfg["unroll"]), int(cfg["batch_size"])
    log_every, last_log = int(cfg["log_every"]), counters["env_steps"]
    last_save, start, start_steps = time.monotonic(), time.perf_counter(), counters["env_steps"]
    returns, completions, step_rewards, losses = [], [], [], []
    cuts, cut_falls, pushed, push_falls = 0, 0, 0, 0
    obs = env.reset()
    stop = StopRequest()
    while counters["env_steps"] < total_steps:
        if stop.requested:  # SIGTERM between unrolls: keep every step taken so far
            save()
            raise SystemExit(f"stopped at env step {counters['env_steps']}; checkpoint saved in {checkpoint}")
        seq_obs, seq_act, seq_rew, seq_disc, seq_logmu = [stored(obs)], [], [], [], []
        done = cut = False
        for _ in range(unroll):
            action, log_mu = learner.act(actor(seq_obs[-1][:obs_size]), rng)
            if pushes is not None:
                pushed += pushes.before_step(env)
            obs, reward, discount, done = env.step(action)
            seq_obs.append(stored(obs))
            seq_act.append(action)
            seq_rew.append(reward)
            seq_disc.append(discount)
            seq_logmu.append(log_mu)
            step_rewards.append(reward)
            counters["env_steps"] += 1
            if done:
                returns.append(env.episode_return)
                completions.append(logic.completion)
                counters["episodes"] += 1
                if pushes is not None and env.layout.logic.contact_failure(env.data) and pushes.fall_follows_push():
                    push_falls += 1
                break
            if cutters:  # cut-ins come at the ends of its fragments, counted from the episode's start
                own = env.layout.logic
                if (own.t - own.start) % fragment_len == 0 and cut_rng.random() < cutting:
                    cut = True  # the unroll ends here, not failed: its last step bootstraps from obs
                    break
        replay.add(**pad_unroll(unroll, seq_obs, seq_act, seq_rew, seq_disc, seq_logmu))
        if pushes is not None and cut:
            pushes.stop(env.data)  # the other skill's fragment plays unpushed
        if done:
            obs = env.reset()
        elif cut:
            obs = cut_in(env, cutters, fragment_len, cut_rng)
            cuts += 1
            if obs is None:  # the other skill's fragment fell: not this expert's episode to learn from
                cut_falls += 1
                obs = env.reset()
        if replay.size >= int(cfg["min_replay_unrolls"]):
            for _ in range(pacer.owed(1)):
                try:
                    taught = None if teacher is None else _sample(teacher, batch_size * unroll, rng)
                    info = learner.update(Batch(**replay.sample(batch_size, rng)),
                                          train_policy=learner.steps >= counters["critic_only_until"], teacher=taught)
                except NonFiniteLoss as error:
                    raise NonFiniteLoss(f"{error} at env step {counters['env_steps']} in {out_dir}; "
                                        f"the last good checkpoint is {checkpoint}") from None
                losses.append(info)
            if learner.steps % int(cfg["publish_every"]) == 0:
                actor = NumpyPolicy.from_torch(policy)
        if counters["env_steps"] - last_log >= log_every:
            last_log = counters["env_steps"]
            row = {"steps_per_second": (counters["env_steps"] - start_steps) / (time.perf_counter() - start),
                   "step_reward": float(np.mean(step_rewards)) if step_rewards else 0.0,
                   "learner_steps": learner.steps}
            if returns:
                row.update(episode_return=float(np.mean(returns)), completion=float(np.mean(completions)))
            if losses:
                row.update({k: float(np.mean([l[k] for l in losses])) for k in losses[0]})
            if cuts:
                row.update(cut_ins=cuts, cut_in_falls=cut_falls / cuts)
            if pushed:
                row.update(pushes=pushed, push_falls=push_falls / pushed)
            metrics.log(counters["env_steps"], row, learner_steps=learner.steps * batch_size * unroll)
            # whole or not at all: the parent's progress bar and a later resume read it while it may be rewritten
            write_atomically(out_dir / "progress.json", json.dumps({"env_steps": counters["env_steps"],
                                                                   "total_steps": total_steps, **row}).encode())
            returns, completions, step_rewards, losses = [], [], [], []
            cuts, cut_falls, pushed, push_falls = 0, 0, 0, 0
        if time.monotonic() - last_save > float(cfg["checkpoint_seconds"]):
            save()
            last_save = time.monotonic()
        if parent_pid is not None and counters["env_steps"] % 1000 < unroll and os.getppid() != parent_pid:
            save()  # the launching process died (killed): keep our progress and stop
            raise SystemExit(f"parent process {parent_pid} is gone; checkpoint saved in {checkpoint}")
    save()
    # scored as `stage=evaluate` scores it: failure by contact only, whatever termination trained it,
    # from the reference's own states; trained with switch starts, from switch states too
    env.layout.logic.termination_error = env.layout.logic.heading_termination = None
    greedy = _greedy(NumpyPolicy.from_torch(policy))
    with switch_starts(env, 0.0):
        final = evaluate(env, greedy, int(cfg["eval_episodes"]), "eval_")
    if switching > 0 or cutting > 0:
        with switch_starts(env, 1.0):
            final.update(evaluate(env, greedy, int(cfg["eval_episodes"]), "eval_switch_"))
    metrics.log(counters["env_steps"], final, learner_steps=learner.steps * batch_size * unroll)
    save()  # its metrics mark now holds the evaluation, which a later, larger total_steps keeps
    metrics.close()
    env.close()
    progress = json.loads((out_dir / "progress.json").read_text()) if (out_dir / "progress.json").exists() else {}
    write_atomically(out_dir / "progress.json", json.dumps({**progress, "env_steps": counters["env_steps"],
                                                           "total_steps": total_steps,
                                                           "learner_steps": learner.steps}).encode())
    return final


def _critic_normalizer(critic: QNetwork, policy: GaussianPolicy) -> None:
    """The critic normalises the policy's inputs as the policy does; its extras (already of
    order 1: a unit quaternion, a velocity in m/s) pass unchanged."""
    extra = critic.normalizer.mean.shape[0] - policy.normalizer.mean.shape[0]
    critic.normalizer.set(np.concatenate([policy.normalizer.mean.numpy(), np.zeros(extra, np.float32)]),
                          np.concatenate([policy.normalizer.std.numpy(), np.ones(extra, np.float32)]))


def _sample(data: tuple[torch.Tensor, ...], size: int, rng: np.random.Generator) -> tuple[torch.Tensor, ...]:
    idx = torch.from_numpy(rng.integers(0, len(data[0]), size))
    return tuple(a[idx] for a in data)


def _greedy(actor: NumpyPolicy):
    return lambda obs, logic: actor(policy_observation(obs))
