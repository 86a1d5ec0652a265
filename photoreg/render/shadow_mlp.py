"""The neural soft-shadow MLP f(u, v, d) -> visibility (Sommer et al., WSCG 2023), numpy only.

Inputs: texture coordinates (u, v) in [0, 1] and the local unit light direction d. Each is mapped to
x = 2 u - 1 (d as is) and positionally encoded as [x, sin(2^k pi x), cos(2^k pi x)] for k < L, with
L = pos_freqs for (u, v) and dir_freqs for d. Then `hidden` ReLU layers of `width` and a sigmoid output.
Training (photoreg.train.neural_soft) and inference share `encode` and `forward`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ShadowMLP:
    """Weights (fan_in, fan_out) and biases of each layer, float32, and the encoding's frequencies."""

    weights: list[np.ndarray]
    biases: list[np.ndarray]
    pos_freqs: int
    dir_freqs: int

    @property
    def n_params(self) -> int:
        return int(sum(w.size + b.size for w, b in zip(self.weights, self.biases)))


def _encode(x: np.ndarray, freqs: int) -> list[np.ndarray]:
    f = (np.pi * 2.0 ** np.arange(freqs, dtype=np.float32))
    a = x[:, :, None] * f                                    # (N, C, L)
    n = len(x)
    return [x, np.sin(a).reshape(n, -1), np.cos(a).reshape(n, -1)]


def encode(uv: np.ndarray, d: np.ndarray, pos_freqs: int, dir_freqs: int) -> np.ndarray:
    """(N, 2 (1 + 2 pos_freqs) + 3 (1 + 2 dir_freqs)) float32 network input of uv (N, 2) and d (N, 3)."""
    x = 2.0 * np.asarray(uv, np.float32) - 1.0
    return np.concatenate(_encode(x, pos_freqs) + _encode(np.asarray(d, np.float32), dir_freqs), axis=1)


def input_size(pos_freqs: int, dir_freqs: int) -> int:
    return 2 * (1 + 2 * pos_freqs) + 3 * (1 + 2 * dir_freqs)


def init_mlp(pos_freqs: int, dir_freqs: int, hidden: int, width: int, rng: np.random.Generator) -> ShadowMLP:
    """He-initialised ReLU layers; the output bias starts at +3 (sigmoid 0.95: most texels are lit)."""
    if hidden < 1 or width < 1 or pos_freqs < 0 or dir_freqs < 0:
        raise ValueError(f"init_mlp: need hidden >= 1, width >= 1, frequencies >= 0 "
                         f"(got {hidden}, {width}, {pos_freqs}, {dir_freqs})")
    sizes = [input_size(pos_freqs, dir_freqs)] + [width] * hidden + [1]
    weights = [(rng.standard_normal((a, b)) * np.sqrt(2.0 / a)).astype(np.float32) for a, b in zip(sizes, sizes[1:])]
    weights[-1] *= 0.1
    biases = [np.zeros(b, np.float32) for b in sizes[1:]]
    biases[-1][:] = 3.0
    return ShadowMLP(weights, biases, pos_freqs, dir_freqs)


def forward(net: ShadowMLP, x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Visibility (N,) of encoded inputs x (N, C), and every layer's input (for backpropagation)."""
    acts = [x]
    h = x
    for w, b in zip(net.weights[:-1], net.biases[:-1]):
        h = np.maximum(h @ w + b, 0.0)
        acts.append(h)
    z = (h @ net.weights[-1] + net.biases[-1])[:, 0]
    return 1.0 / (1.0 + np.exp(-np.clip(z, -30.0, 30.0))), acts


def predict(net: ShadowMLP, uv: np.ndarray, d: np.ndarray, batch: int = 16384) -> np.ndarray:
    """Visibility (N,) float32 at texture coordinates uv (N, 2) for local light directions d (N, 3) or (3,),
    evaluated in batches to bound memory."""
    uv = np.asarray(uv, np.float32).reshape(-1, 2)
    d = np.broadcast_to(np.asarray(d, np.float32), (len(uv), 3))
    out = np.empty(len(uv), np.float32)
    for s in range(0, len(uv), batch):
        out[s:s + batch] = forward(net, encode(uv[s:s + batch], d[s:s + batch], net.pos_freqs, net.dir_freqs))[0]
    return out
