"""The high-level agent (Appendix A, Fig. A.1): encoders -> LSTM core -> heads.

Proprioception is encoded by one linear layer; for vision tasks the camera image (64x64 as in the paper) by an
IMPALA-style ResNet; both, with the previous reward and previous action, are
concatenated into an LSTM whose size is the task's (Table A.1). The policy head is an
LSTM of 128 followed by a linear layer (logits, or a Gaussian's mean and sigma); the
value / Q head is an MLP of the task's sizes. The core ticks every control step.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import nn

from hvc.agents.mlp import mlp
from hvc.config import IMAGE_PRECISIONS


class ResidualBlock(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(torch.relu(self.conv1(torch.relu(x))))


class ImageEncoder(nn.Module):
    """IMPALA ResNet: per stage a conv, a 3x3 max-pool with stride 2 and two residual blocks."""

    def __init__(self, channels: Sequence[int] = (16, 32, 32), out_size: int = 256,
                 image_size: tuple[int, int] = (64, 64), precision: str = "float32"):
        super().__init__()
        if precision not in IMAGE_PRECISIONS:
            raise ValueError(f"image precision {precision!r}; allowed: {', '.join(IMAGE_PRECISIONS)}")
        # bfloat16: the convolutions compute in bfloat16 under autocast (weights, gradients and
        # Adam stay float32), which CPUs with AMX or AVX512-BF16 run several times faster
        # (docs/results/image_precision); the features leave as float32 either way.
        self.autocast = precision == "bfloat16"
        layers: list[nn.Module] = []
        c_in = 3
        for c in channels:
            layers += [nn.Conv2d(c_in, c, 3, padding=1), nn.MaxPool2d(3, stride=2, padding=1),
                       ResidualBlock(c), ResidualBlock(c)]
            c_in = c
        self.body = nn.Sequential(*layers)
        height, width = image_size  # the camera's (render.height, render.width)
        for _ in channels:
            height, width = (height + 1) // 2, (width + 1) // 2
        self.out = nn.Linear(c_in * height * width, out_size)
        # Channels-last conv weights: frames arrive as HWC, and oneDNN's NHWC kernels run the
        # learner's forward + backward faster than mixed layouts (docs/results/design_measurements).
        # (load_state_dict and Adam's moments keep this layout.)
        self.to(memory_format=torch.channels_last)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """image: [..., H, W, 3] uint8."""
        lead = image.shape[:-3]
        x = image.reshape(-1, *image.shape[-3:]).permute(0, 3, 1, 2).float() / 255.0  # an NHWC view, no copy
        with torch.autocast(image.device.type, dtype=torch.bfloat16, enabled=self.autocast):
            x = torch.relu(self.body(x)).flatten(1)
            x = torch.relu(self.out(x))
        return x.float().reshape(*lead, -1)


@dataclass(frozen=True)
class AgentSpec:
    proprio_size: int
    task_size: int
    action_size: int          # discrete: number of choices; continuous: dimension
    discrete: bool
    lstm_size: int            # Table A.1
    value_mlp: tuple[int, ...]  # Table A.1, ending in 1
    vision: bool = False
    proprio_out: int = 128
    policy_lstm: int = 128    # Appendix A: the policy head's LSTM
    critic_takes_action: bool = False  # Q(h, a) for SVG(0) / Wolpertinger
    image_precision: str = "float32"   # the ResNet's compute: float32 or bfloat16 (ImageEncoder)
    image_size: tuple[int, int] = (64, 64)  # (height, width) of the camera frames (the paper's 64x64)


class RunningNormalizer(nn.Module):
    """Running mean and variance of the proprioceptive and task inputs, clipped to +-5 std.

    Raw inputs span orders of magnitude (a rolling ball's gyro reaches 30 rad/s, an
    egocentric target can be 90 m away) and would saturate the LSTM's gates. The statistics
    are buffers: they travel with the weights in checkpoints and to the target agent. So does
    the variance floor: a trained agent reads its inputs through the floor it was trained
    with (changing it under a trained agent wrecks its returns: docs/results/design_measurements/)."""

    DEFAULT_VAR_FLOOR = 1e-2  # std >= 0.1: near-constant inputs (and the first samples) are not blown up

    def __init__(self, size: int, var_floor: float = DEFAULT_VAR_FLOOR):
        super().__init__()
        self.register_buffer("mean", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("var", torch.ones(size, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("var_floor", torch.tensor(float(var_floor), dtype=torch.float64))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints from before the floor was saved: the default floor (warned about by the caller)
        state_dict.setdefault(prefix + "var_floor", torch.tensor(self.DEFAULT_VAR_FLOOR, dtype=torch.float64))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merges a batch of observations (Chan et al.'s parallel variance)."""
        x = x.reshape(-1, self.mean.shape[0]).double()
        n, mean, var = x.shape[0], x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        self.var.copy_((self.var * self.count + var * n + delta ** 2 * self.count * n / total) / total)
        self.mean.add_(delta * n / total)
        self.count.copy_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scaled = (x - self.mean.float()) / torch.sqrt(self.var.float() + self.var_floor.float())
        return torch.clamp(scaled, -5.0, 5.0)


def _run_lstm(lstm: nn.LSTM, x: torch.Tensor, h: torch.Tensor, c: torch.Tensor):
    """A one-layer nn.LSTM over x [T, B, I]. A single step (what acting does every control
    step) goes through torch.lstm_cell with the same weights: the same maths at a fraction of
    nn.LSTM's per-call overhead (docs/results/design_measurements)."""
    if x.shape[0] != 1:
        return lstm(x, (h, c))
    h1, c1 = torch.lstm_cell(x[0], (h[0], c[0]), lstm.weight_ih_l0, lstm.weight_hh_l0,
                             lstm.bias_ih_l0, lstm.bias_hh_l0)
    return h1[None], (h1[None], c1[None])


class HighLevelAgent(nn.Module):
    def __init__(self, spec: AgentSpec):
        super().__init__()
        self.spec = spec
        self.normalizer = RunningNormalizer(spec.proprio_size + spec.task_size)
        self.proprio = nn.Linear(spec.proprio_size + spec.task_size, spec.proprio_out)
        self.image = ImageEncoder(image_size=spec.image_size, precision=spec.image_precision) if spec.vision else None
        core_in = spec.proprio_out + (256 if spec.vision else 0) + 1 + spec.action_size
        self.core = nn.LSTM(core_in, spec.lstm_size)
        self.policy_core = nn.LSTM(spec.lstm_size, spec.policy_lstm)
        self.policy_out = nn.Linear(spec.policy_lstm, spec.action_size if spec.discrete else 2 * spec.action_size)
        value_in = spec.lstm_size + (spec.action_size if spec.critic_takes_action else 0)
        self.value = mlp([value_in, *spec.value_mlp])

    def initial_state(self, batch: int) -> tuple[torch.Tensor, ...]:
        device = self.policy_out.weight.device
        z = lambda n: torch.zeros(1, batch, n, device=device)  # noqa: E731
        return (z(self.spec.lstm_size), z(self.spec.lstm_size), z(self.spec.policy_lstm), z(self.spec.policy_lstm))

    def pack_state(self, state: tuple[torch.Tensor, ...]) -> np.ndarray:
        """The LSTM states as one [batch, 4, hidden] array for the replay (unpack_state undoes it)."""
        hidden = max(self.spec.lstm_size, self.spec.policy_lstm)
        out = np.zeros((state[0].shape[1], 4, hidden), np.float32)
        for k, s in enumerate(state):
            out[:, k, :s.shape[-1]] = s[0].cpu().numpy()
        return out

    def unpack_state(self, packed: torch.Tensor) -> tuple[torch.Tensor, ...]:
        sizes = (self.spec.lstm_size, self.spec.lstm_size, self.spec.policy_lstm, self.spec.policy_lstm)
        return tuple(packed[:, k, :n][None].contiguous() for k, n in enumerate(sizes))

    def forward(self, proprio: torch.Tensor, task: torch.Tensor, prev_reward: torch.Tensor,
                prev_action: torch.Tensor, state: tuple[torch.Tensor, ...], image: torch.Tensor | None = None,
                done: torch.Tensor | None = None):
        """Time-major inputs [T, B, ...]; `done` [T, B] resets the LSTM state before a step
        that starts a new episode. Returns (policy output, core features h, new state)."""
        feats = [torch.relu(self.proprio(self.normalizer(torch.cat([proprio, task], -1))))]
        if self.image is not None:
            feats.append(self.image(image))
        if self.spec.discrete:
            prev = nn.functional.one_hot(prev_action.long(), self.spec.action_size).float()
        else:
            prev = prev_action
        x = torch.cat(feats + [prev_reward[..., None], prev], -1)
        h_c, c_c, h_p, c_p = state
        core_out, policy_out = [], []
        # one LSTM call per stretch of steps without an episode start in any batch row (most
        # unrolls are a single stretch): far fewer Python-level calls than stepping one by one
        T = x.shape[0]
        starts = [0] if done is None else sorted({0, *torch.nonzero(done.reshape(T, -1).any(-1)).flatten().tolist()})
        for t0, t1 in zip(starts, starts[1:] + [T]):
            if done is not None:
                keep = (1.0 - done[t0].float())[None, :, None]
                h_c, c_c, h_p, c_p = h_c * keep, c_c * keep, h_p * keep, c_p * keep
            out, (h_c, c_c) = _run_lstm(self.core, x[t0:t1], h_c, c_c)
            pol, (h_p, c_p) = _run_lstm(self.policy_core, out, h_p, c_p)
            core_out.append(out)
            policy_out.append(pol)
        h = torch.cat(core_out, 0)
        return self.policy_out(torch.cat(policy_out, 0)), h, (h_c, c_c, h_p, c_p)

    def values(self, h: torch.Tensor, action: torch.Tensor | None = None) -> torch.Tensor:
        inputs = h if action is None else torch.cat([h, action], -1)
        return self.value(inputs).squeeze(-1)

    def gaussian(self, policy_output: torch.Tensor, low: float, high: float, sigma_clip=(0.1, 1.0)):
        """Steering-style Gaussian: tanh-squashed mean scaled to [low, high], sigma bounded to
        `sigma_clip` by a sigmoid rather than a clamp, so that a sigma at its floor still has a
        gradient (a clamped one stays at the floor for good once it gets there)."""
        mean_raw, sigma_raw = policy_output.chunk(2, -1)
        scale, centre = (high - low) / 2, (high + low) / 2
        mean = centre + scale * torch.tanh(mean_raw)
        floor, ceiling = sigma_clip
        sigma = floor + (ceiling - floor) * torch.sigmoid(sigma_raw)
        return mean, sigma
