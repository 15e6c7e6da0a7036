"""`hvc-bench`: env throughput against the raw physics ceiling, measured in one run.

Per task: the raw `mj_step` rate on the same compiled model (the ceiling, expressed in
control steps/s), the hvc fast env's control steps/s with random actions including
resets, dm_control composer's on the same task, and the mean reset time of each. Then
64x64 camera frames/s on gaps with the default and the fast render settings, and the
time of one low-level expert's action (numpy float32, hidden 256) against its 30 us goal,
and for fragments on go_to_target and gaps the actor's env steps/s (env + experts + camera)
and the V-trace learner's transitions/s at the task's Table A.1 sizes (on gaps, with the
image encoder in float32 and in bfloat16: `image_precision`, their ratio). Then two envs of the
rolling ball (end_to_end) and of the humanoid (fragments) stepped by VectorEnv with 0, 1 or 2
of them in the main process, against twice one env's rate stepped directly (the ceiling of
two cores; the humanoid's goal is 0.85 with one of them in the main process). Then a short
real training run (fragments on go_to_target) against its actor-only and learner-only rates
measured in the same call: the two fractions should add up to 0.9 or more, or a core waits.
Last, Ray actors acting against the local worker processes (`--only ray`). `--only` picks lines. Ratios, not absolute times, are the numbers to compare across machines.
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # per-core numbers: one thread, before numpy loads BLAS

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from hvc.config import compose  # noqa: E402
from hvc.envs.builders import build_composer_env  # noqa: E402
from hvc.envs.fast_env import FastEnv  # noqa: E402
from hvc.envs.render import CameraRenderer  # noqa: E402

TASKS = ("go_to_target", "walls", "gaps", "forage", "heterogeneous_forage")
EPISODE_CAP = 40  # control steps: longer than random actions keep the humanoid up


def _plain(cfg, key):
    from omegaconf import OmegaConf
    return OmegaConf.to_container(cfg[key], resolve=True)


def hvc_sps(env: FastEnv, seconds: float):
    """Fast env control steps/s with random actions including resets, the mean reset ms,
    and the episodes it ran (start state + actions) so the ceiling replays the same physics."""
    episodes, reset_time, n, length = [], 0.0, 0, 0
    env.reset()
    episodes.append((env.data.qpos.copy(), env.data.qvel.copy(), env.model, []))
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        action = env.random_action()
        episodes[-1][3].append(action)
        done = env.step(action)[3]
        n += 1
        length += 1
        if done or length >= EPISODE_CAP:
            r0 = time.perf_counter()
            env.reset()
            reset_time += time.perf_counter() - r0
            episodes.append((env.data.qpos.copy(), env.data.qvel.copy(), env.model, []))
            length = 0
    sps = n / (time.perf_counter() - t0)
    return sps, 1000 * reset_time / max(len(episodes) - 1, 1), episodes


def ceiling_sps(env: FastEnv, episodes) -> float:
    """Raw mj_step replaying the same episodes (same models, states and actions), in control steps/s."""
    actuators, substeps, n = env.layout.actuators, env.n_substeps, 0
    datas = {id(layout.model): mujoco.MjData(layout.model) for layout in env.layouts}
    t0 = time.perf_counter()
    for qpos, qvel, model, actions in episodes:
        data = datas[id(model)]
        data.qpos[:], data.qvel[:], data.time = qpos, qvel, 0.0
        for action in actions:
            data.ctrl[actuators] = action
            mujoco.mj_step(model, data, substeps)
        n += len(actions)
    return n / (time.perf_counter() - t0)


def composer_sps(task, body, seconds: float, rng) -> tuple[float, float]:
    """dm_control composer's control steps/s (random actions, resets included) and reset ms."""
    env = build_composer_env(task, body, seed=0)
    spec = env.action_spec()
    resets, reset_time, n, length = 0, 0.0, 0, 0
    env.reset()
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        step = env.step(rng.uniform(spec.minimum, spec.maximum))
        n += 1
        length += 1
        if step.last() or length >= EPISODE_CAP:
            r0 = time.perf_counter()
            env.reset()
            reset_time += time.perf_counter() - r0
            resets += 1
            length = 0
    sps = n / (time.perf_counter() - t0)
    env.close()
    return sps, 1000 * reset_time / max(resets, 1)


def render_fps(settings_name: str, seconds: float) -> float:
    cfg = compose(["task=gaps", f"render={settings_name}", "task.layout_pool=1"])
    env = FastEnv.build(_plain(cfg, "task"), _plain(cfg, "body"), _plain(cfg, "render"), render=False)
    env.reset()
    renderer = CameraRenderer(env.model, env.layout.camera, _plain(cfg, "render"))
    out = np.empty((64, 64, 3), np.uint8)
    renderer.render(env.data, out=out)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        renderer.render(env.data, out=out)
        n += 1
    fps = n / (time.perf_counter() - t0)
    renderer.close()
    env.close()
    return fps


def expert_inference_us(hidden: int, seconds: float) -> float:
    """One expert's action for one env step (numpy float32, one thread), microseconds."""
    import torch

    from hvc.agents.mlp import GaussianPolicy, NumpyPolicy

    torch.manual_seed(0)
    cfg = compose(["stage=lowlevel", "task=tracking"])
    obs_size = 136 + 1  # the humanoid's proprioception + the time input
    actor = NumpyPolicy.from_torch(GaussianPolicy(obs_size, 56, [hidden, hidden], float(cfg.lowlevel.sigma)))
    obs = np.random.default_rng(0).normal(size=obs_size).astype(np.float32)
    for _ in range(200):
        actor(obs)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for _ in range(100):
            actor(obs)
        n += 100
    return 1e6 * (time.perf_counter() - t0) / n


def _bench_library(clip_set: str = "go_to_target"):
    """The clip set's shipped library (gaps: 359 fragments), else the default one, else random
    experts of the default set's shapes (throughput only)."""
    import torch

    from hvc.agents.mlp import GaussianPolicy, NumpyPolicy
    from hvc.lowlevel.library import Expert, ExpertLibrary, SHIPPED_DIR
    from hvc.mocap.reference import Reference

    for name in (clip_set, "go_to_target"):
        if (SHIPPED_DIR / f"experts_{name}.npz").exists():
            return ExpertLibrary.load(SHIPPED_DIR / f"experts_{name}.npz")
    experts = []
    for i, n in enumerate((102, 108, 43, 58)):  # the default set's lengths: 105 fragments at length 3
        torch.manual_seed(i)
        z = np.zeros
        ref = Reference(f"CMU_{i}", 0.03, False, z((n, 56)), z((n, 56)), z((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)),
                        z((n, 3)), z((n, 3)), z((n, 4, 3)), np.linspace(0, 1, n))
        experts.append(Expert({"id": f"CMU_{i}", "behaviour": str(i), "start": 0, "end": n},
                              NumpyPolicy.from_torch(GaussianPolicy(137, 56, [256, 256], 0.1)), ref))
    return ExpertLibrary(experts, {})


def hl_throughput(task_name: str, seconds: float) -> tuple[float, dict[tuple[int, str], float]]:
    """(actor env steps/s through the fragments controller, {(torch threads, image precision):
    learner transitions/s of V-trace}): on vision tasks at one thread and torch_threads=auto's
    every core, each in both image precisions."""
    import torch

    from hvc.agents.network import AgentSpec, HighLevelAgent
    from hvc.controllers.base import ControlledEnv
    from hvc.controllers.fragments import FragmentsController
    from hvc.algorithms.replay import UnrollReplay
    from hvc.algorithms.vtrace import VTraceLearner
    from hvc.config import IMAGE_PRECISIONS
    from hvc.runtime.hl_train import unroll_fields
    from hvc.skills import Skills

    torch.set_num_threads(1)
    cfg = compose([f"task={task_name}", "task.layout_pool=1", "task.init_from_clips=false"])
    env = FastEnv.build(_plain(cfg, "task"), _plain(cfg, "body"), _plain(cfg, "render"), seed=0)
    controlled = ControlledEnv(env, FragmentsController(Skills.from_library(_bench_library(str(cfg.clips.name)), 3)))
    rng = np.random.default_rng(0)
    controlled.reset()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        done = controlled.step(int(rng.integers(controlled.action_space.n)) if controlled.needs_action else None)[3]
        n += 1
        if done:
            controlled.reset()
    actor_sps = n / (time.perf_counter() - t0)
    agent_cfg = cfg.task.agent
    vision = bool(cfg.task.vision)
    sizes = env.layout.proprio.size, env.layout.logic.observation_size, controlled.action_space.n
    env.close()
    precisions = IMAGE_PRECISIONS if vision else ("float32",)
    learners = {}
    for precision in precisions:
        spec = AgentSpec(*sizes, True, int(agent_cfg.lstm_size), tuple(agent_cfg.value_mlp), vision,
                         image_precision=precision)
        learners[precision] = VTraceLearner.from_config(HighLevelAgent(spec), cfg)
    unroll, batch = int(agent_cfg.unroll), int(cfg.algorithm.batch_size)
    replay = UnrollReplay(batch * 2, unroll_fields(spec, unroll))
    replay.size = replay.capacity
    replay.arrays["action"][:] = rng.integers(0, spec.action_size, replay.arrays["action"].shape)
    replay.arrays["new_action"][:] = 1.0
    # interleaved blocks, so that the machine's drift hits every variant alike
    variants = [(threads, precision) for threads in sorted({1, int(cfg.torch_threads)}) for precision in precisions]
    updates, elapsed = dict.fromkeys(variants, 0), dict.fromkeys(variants, 0.0)
    blocks = 3
    for _ in range(blocks):
        for threads, precision in variants:
            torch.set_num_threads(threads)
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < seconds / blocks or updates[threads, precision] < 2:
                learners[precision].update(replay.sample(batch, rng))
                updates[threads, precision] += 1
            elapsed[threads, precision] += time.perf_counter() - t0
    torch.set_num_threads(1)
    return actor_sps, {v: updates[v] * batch * unroll / elapsed[v] for v in variants}


def _interleaved_sps(variants: dict, seconds: float, rng: np.random.Generator, blocks: int = 5) -> dict:
    """Env steps/s of each batched env in `variants` under random actions, measured in
    interleaved blocks so that the machine's drift hits every variant alike."""
    elapsed, steps = dict.fromkeys(variants, 0.0), dict.fromkeys(variants, 0)
    for envs in variants.values():
        envs.reset()
    for _ in range(blocks):
        for key, envs in variants.items():
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < seconds / blocks:
                envs.step(envs.random_actions(rng))
                steps[key] += envs.num_envs
            elapsed[key] += time.perf_counter() - t0
    return {key: steps[key] / elapsed[key] for key in variants}


def vector_env_sps(overrides: list[str], seconds: float, num_envs: int = 2) -> tuple[float, dict[int, float]]:
    """(ceiling: num_envs x one env's steps/s, {in_process: env steps/s of VectorEnv}) with
    random high-level actions, measured in interleaved blocks so that the machine's drift
    hits every variant alike."""
    from omegaconf import OmegaConf

    from hvc.controllers.factory import Drive
    from hvc.envs.vector_env import VectorEnv
    from hvc.runtime.env_config import env_dicts
    from hvc.skills import skills_for_job

    cfg = compose(overrides)
    task, body, render = env_dicts(cfg)
    controller = OmegaConf.to_container(cfg.controller, resolve=True)
    variants: dict = {}
    rng = np.random.default_rng(0)
    try:
        for key, n, in_process in [("single", 1, 1)] + [(k, num_envs, k) for k in range(num_envs + 1)]:
            variants[key] = VectorEnv(task, body, render, n, seed=0, drive=Drive(controller, skills_for_job(cfg)),
                                      in_process=in_process)
        rate = _interleaved_sps(variants, seconds, rng)
    finally:
        for envs in variants.values():
            envs.close()
    return num_envs * rate.pop("single"), rate


def ray_actors_sps(overrides: list[str], seconds: float, num_envs: int = 2) -> dict[str, float]:
    """Acting rates (env steps/s with the high-level agent choosing the actions, unrolls built
    for replay, no learning) of a run's local backend (worker processes and this one, the
    policy batched here) against Ray actors on this machine (ray.init, loopback) acting with
    their own copies of the agent (whole unrolls, weights broadcast). Interleaved in blocks so
    that the machine's drift hits both alike. Central acting through Ray (ray.acting=central)
    is left out: its compiled graph's channels poll a core even while the other variant runs."""
    import torch

    from hvc.runtime.acting import Actor, LocalActing
    from hvc.runtime.hl_train import build_agent, make_envs, unroll_fields
    from hvc.runtime.ray_acting import RayActing

    torch.set_num_threads(1)
    torch.manual_seed(0)
    base = overrides + [f"num_envs={num_envs}"]
    cfg = compose(base)
    n = int(cfg.task.agent.unroll)
    local_envs = make_envs(cfg)
    spec, agent, learner = build_agent(cfg, local_envs)
    names = unroll_fields(spec, n, query=learner.keeps_query)
    variants = {"local": LocalActing(Actor(agent, learner, local_envs), n, names)}
    try:
        in_actors = compose(base + ["actors=ray", "ray.acting=actors", f"ray.num_cpus={num_envs}"])
        variants["actors"] = RayActing(in_actors, int(cfg.seed), run_dir=None).attach(agent)  # records nothing
        variants["actors"].publish(0)
        for acting in variants.values():
            acting.collect()  # start-up (the actors' first unrolls, the workers' first steps) left out
        elapsed, steps = dict.fromkeys(variants, 0.0), dict.fromkeys(variants, 0)
        blocks = 5
        for _ in range(blocks):
            for key, acting in variants.items():
                t0 = time.perf_counter()
                while time.perf_counter() - t0 < seconds / blocks:
                    steps[key] += acting.collect().env_steps
                    acting.publish(0)
                elapsed[key] += time.perf_counter() - t0
    finally:
        for acting in variants.values():
            acting.close()
    return {key: steps[key] / elapsed[key] for key in variants}


def training_balance(overrides: list[str], seconds: float, total_steps: int) -> dict[str, float]:
    """Does a training run keep the cores busy? A short real `stage=train` run (the same
    `run_hl_training` as `hvc-run`) against the rates of its two halves measured alone in the
    same call: the actor-only rate (the run's envs and agent acting, unrolls written to replay,
    no updates) and the learner-only rate (updates at the run's torch_threads on what that
    acting stored). Acting and learning take turns in one process, so the two fractions of
    their alone-rates add up to at most about 1; time lost to neither (waiting, logging,
    checkpoints) shows up as a sum below 1. The training rates count from its first metrics
    row to its last, so start-up (workers, experts) is left out. Alone-rates: two blocks each,
    before and after the run, so that the machine's drift hits both sides alike."""
    import tempfile
    from pathlib import Path

    import pandas as pd
    import torch

    from hvc.algorithms.replay import UnrollReplay
    from hvc.runtime.acting import Actor, LocalActing
    from hvc.runtime.hl_train import build_agent, make_envs, run_hl_training, unroll_fields

    cfg = compose(overrides + [f"total_steps={total_steps}", "hl.random_episodes=0", "progress_seconds=1e9"])
    n, batch = int(cfg.task.agent.unroll), int(cfg.algorithm.batch_size)
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    envs = make_envs(cfg)
    spec, agent, learner = build_agent(cfg, envs)
    replay = UnrollReplay(4096, unroll_fields(spec, n, query=learner.keeps_query))
    acting = LocalActing(Actor(agent, learner, envs), n, replay.fields)
    act_time = act_steps = learn_time = learn_transitions = 0.0

    def act_alone():
        nonlocal act_time, act_steps
        torch.set_num_threads(1)
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds / 2 or replay.size < batch:
            collected = acting.collect()
            for unroll in collected.unrolls:
                replay.add(**unroll)
            act_steps += collected.env_steps
        act_time += time.perf_counter() - t0

    def learn_alone():
        nonlocal learn_time, learn_transitions
        torch.set_num_threads(int(cfg.torch_threads))
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds / 2:
            learner.update(replay.sample(batch, rng))
            learn_transitions += batch * n
        learn_time += time.perf_counter() - t0
        torch.set_num_threads(1)

    try:
        act_alone()
        learn_alone()
        with tempfile.TemporaryDirectory() as run_dir:
            run_hl_training(cfg, Path(run_dir))
            rows = pd.read_csv(Path(run_dir) / "metrics.csv").drop_duplicates("env_steps")
        act_alone()
        learn_alone()
    finally:
        envs.close()
        torch.set_num_threads(1)
    first, last = rows.iloc[0], rows.iloc[-1]
    wall = last.wall_time - first.wall_time
    out = {"train_sps": (last.env_steps - first.env_steps) / wall,
           "train_tps": (last.learner_steps - first.learner_steps) / wall,
           "actor_sps": act_steps / act_time, "learner_tps": learn_transitions / learn_time}
    out["sum"] = out["train_sps"] / out["actor_sps"] + out["train_tps"] / out["learner_tps"]
    return out


SECTIONS = ("tasks", "hl", "expert", "render", "vector_env", "train", "ray")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument("--only", nargs="+", default=list(SECTIONS), choices=SECTIONS,
                        help="measure these lines only (default: all)")
    parser.add_argument("--seconds", type=float, default=3.0, help="per measurement")
    parser.add_argument("--no-composer", action="store_true", help="skip dm_control composer (slow resets)")
    parser.add_argument("--no-render", action="store_true")
    parser.add_argument("--train-steps", type=int, default=6000, help="env steps of the short training run")
    parser.add_argument("--no-ray", action="store_true", help="skip the Ray actors line (needs hvc[ray])")
    args = parser.parse_args(argv)
    only = set(args.only) - ({"render"} if args.no_render else set()) - ({"ray"} if args.no_ray else set())
    rng = np.random.default_rng(0)
    lines = []
    if "tasks" in only:
        print(f"{'task':<22}{'ceiling sps':>12}{'hvc sps':>10}{'composer sps':>14}{'hvc/ceil':>10}"
              f"{'reset ms':>10}{'composer reset ms':>19}")
    for name in args.tasks if "tasks" in only else ():
        cfg = compose([f"task={name}"])
        task, body, render = (_plain(cfg, k) for k in ("task", "body", "render"))
        env = FastEnv.build(task, body, render, seed=0, render=False)
        sps, reset_ms, episodes = hvc_sps(env, args.seconds)
        ceiling = ceiling_sps(env, episodes)
        env.close()
        comp, comp_reset = (float("nan"),) * 2 if args.no_composer else composer_sps(task, body, args.seconds, rng)
        print(f"{name:<22}{ceiling:>12.0f}{sps:>10.0f}{comp:>14.0f}{sps / ceiling:>10.2f}"
              f"{reset_ms:>10.2f}{comp_reset:>19.1f}", flush=True)
        lines.append(f"bench task={name} ceiling_sps={ceiling:.0f} hvc_sps={sps:.0f} composer_sps={comp:.0f} "
                     f"hvc/ceiling={sps / ceiling:.2f} composer/ceiling={comp / ceiling:.2f} "
                     f"reset_ms={reset_ms:.2f} composer_reset_ms={comp_reset:.1f}")
    for name in ("go_to_target", "gaps") if "hl" in only else ():
        actor, learner = hl_throughput(name, args.seconds)
        lines.append(f"bench hl task={name} controller=fragments actor_sps={actor:.0f} "
                     f"learner_tps={learner[1, 'float32']:.0f}"
                     + "".join(f" learner_tps_{k}_threads={v:.0f}" for (k, p), v in learner.items()
                               if k > 1 and p == "float32"))
        for threads in sorted({k for k, p in learner if p == "bfloat16"}):
            lines.append(f"bench image_precision task={name} threads={threads} "
                         f"float32_tps={learner[threads, 'float32']:.0f} "
                         f"bfloat16_tps={learner[threads, 'bfloat16']:.0f} "
                         f"ratio={learner[threads, 'bfloat16'] / learner[threads, 'float32']:.2f}")
    if "expert" in only:
        us = expert_inference_us(256, args.seconds)
        lines.append(f"bench expert_inference hidden=256 us_per_step={us:.1f} goal_us=30 ratio={us / 30:.2f}")
    for settings in ("default", "fast") if "render" in only else ():
        lines.append(f"bench render task=gaps settings={settings} size=64x64 "
                     f"fps={render_fps(settings, args.seconds):.0f}")
    for overrides in (["body=rolling_ball", "controller=end_to_end"], ["controller=fragments"]) \
            if "vector_env" in only else ():
        ceiling, rates = vector_env_sps(overrides + ["task=go_to_target"], args.seconds)
        lines.append(f"bench vector_env {' '.join(overrides)} num_envs=2 ceiling_sps={ceiling:.0f} " + " ".join(
            f"in_process={k}:sps={v:.0f},ratio={v / ceiling:.2f}" for k, v in rates.items()) + " goal=0.85")
    if "train" in only:
        overrides = ["controller=fragments", "task=go_to_target"]
        b = training_balance(overrides, args.seconds, args.train_steps)
        lines.append(f"bench train {' '.join(overrides)} train_sps={b['train_sps']:.0f} actor_sps={b['actor_sps']:.0f} "
                     f"train_tps={b['train_tps']:.0f} learner_tps={b['learner_tps']:.0f} "
                     f"sum={b['sum']:.2f} goal=0.9")
    if "ray" in only:
        rates = ray_actors_sps(["controller=fragments", "task=go_to_target"], args.seconds)
        lines.append(f"bench ray_actors controller=fragments num_envs=2 acting local_sps={rates['local']:.0f} "
                     f"ray_actors_sps={rates['actors']:.0f} "
                     f"ratio={rates['actors'] / rates['local']:.2f} goal=0.8")
    print()
    for line in lines:
        print(line)


if __name__ == "__main__":
    main()
