"""MLP policy and critic for the low-level experts, with a float32 numpy twin for actors.

The policy is a Gaussian with a tanh-bounded mean and a FIXED standard deviation (the
paper: learning the variance converged prematurely). Actors run the numpy twin: one
expert step costs a few matrix-vector products, no torch dispatch.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import nn


def mlp(sizes: Sequence[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(nn.ELU())
    return nn.Sequential(*layers)


class Normalizer(nn.Module):
    """Fixed observation normalisation (mean, std) stored with the weights."""

    def __init__(self, size: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(size))
        self.register_buffer("std", torch.ones(size))

    def set(self, mean: np.ndarray, std: np.ndarray) -> None:
        self.mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.std.copy_(torch.as_tensor(np.maximum(std, 1e-3), dtype=torch.float32))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.clamp((obs - self.mean) / self.std, -10.0, 10.0)


class GaussianPolicy(nn.Module):
    """tanh(MLP) mean, fixed sigma. It reads the first `obs_size` columns of what it is given,
    so a learner may store wider states whose extra columns only its critic sees."""

    def __init__(self, obs_size: int, action_size: int, hidden: Sequence[int], sigma: float):
        super().__init__()
        self.obs_size = int(obs_size)
        self.normalizer = Normalizer(obs_size)
        self.net = mlp([obs_size, *hidden, action_size])
        self.sigma = float(sigma)

    @classmethod
    def from_weights(cls, weights: dict, hidden: Sequence[int], sigma: float) -> "GaussianPolicy":
        """A policy from a checkpoint's state dict, its input and action sizes read off the weights."""
        obs_size = weights["normalizer.mean"].shape[0]
        action_size = [v for k, v in weights.items() if k.endswith("bias")][-1].shape[0]
        policy = cls(obs_size, action_size, hidden, sigma)
        policy.load_state_dict(weights)
        return policy

    def mean(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(self.normalizer(obs[..., :self.obs_size])))


def gaussian_log_prob(action: torch.Tensor, mean: torch.Tensor, sigma: float) -> torch.Tensor:
    z = (action - mean) / sigma
    return (-0.5 * z.pow(2) - np.log(sigma) - 0.5 * np.log(2 * np.pi)).sum(-1)


class QNetwork(nn.Module):
    def __init__(self, obs_size: int, action_size: int, hidden: Sequence[int]):
        super().__init__()
        self.normalizer = Normalizer(obs_size)
        self.net = mlp([obs_size + action_size, *hidden, 1])

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([self.normalizer(obs), action], -1)).squeeze(-1)


class NumpyPolicy:
    """float32 numpy inference of a GaussianPolicy's mean: tanh(MLP((obs - m) / s))."""

    def __init__(self, weights: list[np.ndarray], biases: list[np.ndarray], obs_mean: np.ndarray,
                 obs_std: np.ndarray):
        self.weights = [np.ascontiguousarray(w, np.float32) for w in weights]
        self.biases = [np.ascontiguousarray(b, np.float32) for b in biases]
        self.inv_std = (1.0 / np.maximum(obs_std, 1e-3)).astype(np.float32)
        self.mean_obs = obs_mean.astype(np.float32)

    @classmethod
    def from_torch(cls, policy: GaussianPolicy) -> "NumpyPolicy":
        linears = [m for m in policy.net if isinstance(m, nn.Linear)]
        return cls([m.weight.detach().numpy().T.copy() for m in linears],
                   [m.bias.detach().numpy().copy() for m in linears],
                   policy.normalizer.mean.numpy().copy(), policy.normalizer.std.numpy().copy())

    def with_fixed_inputs(self, tail: np.ndarray) -> "NumpyPolicy":
        """The same policy with its last inputs held at `tail`, folded into the first layer's
        bias: it takes the other inputs only and acts exactly as before (the switching policy
        with one behaviour's code, played as that behaviour's expert)."""
        tail = np.asarray(tail, np.float32)
        n = len(tail)
        held = np.clip((tail - self.mean_obs[-n:]) * self.inv_std[-n:], -10.0, 10.0)
        first, rest = self.weights[0], self.weights[1:]
        return NumpyPolicy([first[:-n], *rest], [self.biases[0] + held @ first[-n:], *self.biases[1:]],
                           self.mean_obs[:-n], 1.0 / self.inv_std[:-n])

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """One observation (1-D) or a batch (2-D). The 1-D path reuses preallocated
        buffers: a step of the humanoid's expert is a few small matrix-vector products,
        so allocation and call overhead matter as much as the arithmetic."""
        if np.ndim(obs) != 1:
            return self._batch(np.asarray(obs, np.float32))
        buffers = self._buffers
        x = buffers[0]
        np.subtract(obs, self.mean_obs, out=x)
        np.multiply(x, self.inv_std, out=x)
        np.clip(x, -10.0, 10.0, out=x)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = buffers[i + 1]
            np.dot(x, w, out=h)
            h += b
            if i < last:  # ELU in place: max(h, 0) + expm1(min(h, 0))
                neg = self._neg[i]
                np.minimum(h, 0.0, out=neg)
                np.expm1(neg, out=neg)
                np.maximum(h, 0.0, out=h)
                h += neg
            x = h
        return np.tanh(x)

    @property
    def _buffers(self) -> list[np.ndarray]:
        if not hasattr(self, "_bufs"):
            self._bufs = [np.empty(self.weights[0].shape[0], np.float32)] + [
                np.empty(w.shape[1], np.float32) for w in self.weights]
            self._neg = [np.empty(w.shape[1], np.float32) for w in self.weights]
        return self._bufs

    def _batch(self, obs: np.ndarray) -> np.ndarray:
        h = np.clip((obs - self.mean_obs) * self.inv_std, -10.0, 10.0)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = h @ w + b
            if i < last:
                h = np.maximum(h, 0.0) + np.expm1(np.minimum(h, 0.0))
        return np.tanh(h)
