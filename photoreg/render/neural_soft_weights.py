"""Neural soft-shadow weights on disk: training settings, the per-mesh key, where weights are looked up
(the user cache, then the ones committed under data/weights/neural_soft) and the .npz format.

key = sha256(mesh file bytes + the settings as canonical JSON [+ the mesh's up when it is not its +z]), first 16 hex
digits: a changed mesh, setting or up never reuses stale weights. The file holds W0.., b0.. (float16) and a JSON
`meta` string with the settings, the mesh's sha256, its up and the training figures.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from photoreg.io.atomic import atomic_path
from photoreg.render.shadow_mlp import ShadowMLP, input_size

COMMITTED_DIR = Path(__file__).resolve().parents[2] / "data" / "weights" / "neural_soft"


@dataclass(frozen=True)
class NeuralSoftSettings:
    """Everything that shapes the weights: training set, network, optimiser (defaults: Sommer et al.)."""

    resolution: int = 256          # texels per texture side
    theta_max_deg: float = 45.0    # light zenith angles 0 .. theta_max
    theta_step_deg: float = 4.5
    phi_step_deg: float = 12.0
    cone_deg: float = 20.0         # full opening angle of the area light
    rays: int = 64                 # stratified cone rays per texel (a square number)
    hidden: int = 3                # hidden ReLU layers
    width: int = 128
    pos_freqs: int = 10            # positional-encoding frequencies for (u, v)
    dir_freqs: int = 4             # ... for the light direction
    steps: int = 12000             # Adam steps
    batch: int = 4096              # bilinear texture samples per step
    lr: float = 2e-3               # initial learning rate
    lr_final: float = 5e-5         # exponential decay reaches this at the last step
    seed: int = 0

    def check(self) -> "NeuralSoftSettings":
        """self, or ValueError naming the bad field."""
        m = int(round(np.sqrt(self.rays)))
        for name, ok in [("resolution", self.resolution >= 2), ("rays", self.rays >= 1 and m * m == self.rays),
                         ("theta_step_deg", self.theta_step_deg > 0), ("phi_step_deg", self.phi_step_deg > 0),
                         ("theta_max_deg", 0 <= self.theta_max_deg < 90), ("cone_deg", 0 < self.cone_deg < 180),
                         ("steps", self.steps >= 1), ("batch", self.batch >= 1),
                         ("lr", 0 < self.lr_final <= self.lr)]:
            if not ok:
                raise ValueError(f"neural_soft settings: bad {name} ({asdict(self)})")
        return self


def mesh_sha256(mesh_path: str | os.PathLike) -> str:
    """sha256 hex digest of a mesh file's bytes; FileNotFoundError naming it."""
    path = Path(mesh_path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: mesh file not found")
    return hashlib.sha256(path.read_bytes()).hexdigest()


def standing_rotation(up: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) from the mesh's own frame to the frame its shadow textures are made in, whose +z is the
    mesh's `up` (a signed unit axis of the mesh: the side it stands on, neural_soft.support_axis); the turn of least
    angle, half a turn about x for -z, the identity for +z."""
    z = np.array([0.0, 0.0, 1.0])
    c, v = float(up @ z), np.cross(up, z)
    if c <= -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


AXES = ("+x", "+y", "+z", "-x", "-y", "-z")   # the sides a mesh can stand on, by the axis of its frame that is up


def axis_name(up: np.ndarray) -> str:
    """'+y' for the unit axis (0, 1, 0), and so on (AXES)."""
    k = int(np.argmax(np.abs(up)))
    return ("+" if up[k] > 0 else "-") + "xyz"[k]


def axis_vector(name: str) -> np.ndarray:
    """The unit axis (3,) of a name of AXES; ValueError otherwise."""
    if name not in AXES:
        raise ValueError(f"up {name!r}: one of {', '.join(AXES)}")
    v = np.zeros(3)
    v["xyz".index(name[1])] = 1.0 if name[0] == "+" else -1.0
    return v


def weights_key(mesh_path: str | os.PathLike, settings: NeuralSoftSettings, up: np.ndarray | None = None) -> str:
    """16 hex digits identifying (mesh bytes, settings, the mesh's up: standing_rotation; None or +z: upright)."""
    h = hashlib.sha256(mesh_sha256(mesh_path).encode())
    h.update(json.dumps(asdict(settings), sort_keys=True).encode())
    if up is not None and not np.array_equal(np.asarray(up, np.float64), [0.0, 0.0, 1.0]):
        h.update(json.dumps((np.asarray(up, np.float64) + 0.0).tolist()).encode())   # + 0.0: no -0.0
    return h.hexdigest()[:16]


def cache_dir() -> Path:
    """$PHOTOREG_CACHE/neural_soft, else ~/.cache/photoreg/neural_soft."""
    root = os.environ.get("PHOTOREG_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "photoreg") / "neural_soft"


def find_weights(key: str) -> Path | None:
    """The first existing <key>.npz in the cache, then among the committed weights."""
    for folder in (cache_dir(), COMMITTED_DIR):
        p = folder / f"{key}.npz"
        if p.is_file():
            return p
    return None


def save_weights(path: str | os.PathLike, net: ShadowMLP, meta: dict) -> Path:
    """Write the net (float16) and its meta atomically."""
    arrays = {f"W{k}": w.astype(np.float16) for k, w in enumerate(net.weights)}
    arrays |= {f"b{k}": b.astype(np.float16) for k, b in enumerate(net.biases)}
    meta = dict(meta, pos_freqs=net.pos_freqs, dir_freqs=net.dir_freqs)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays)
    return Path(path)


def load_weights(path: str | os.PathLike) -> tuple[ShadowMLP, dict]:
    """(net in float32, meta) from a weights file; ValueError naming the file when malformed."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            n = sum(1 for k in z.files if k.startswith("W"))
            weights = [z[f"W{k}"].astype(np.float32) for k in range(n)]
            biases = [z[f"b{k}"].astype(np.float32) for k in range(n)]
        net = ShadowMLP(weights, biases, int(meta["pos_freqs"]), int(meta["dir_freqs"]))
    except (OSError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: not a neural_soft weights file ({e})") from None
    sizes = [input_size(net.pos_freqs, net.dir_freqs)] + [len(b) for b in biases]
    if n < 2 or any(w.shape != (a, b) for w, a, b in zip(weights, sizes, sizes[1:])) or sizes[-1] != 1 \
            or not all(np.all(np.isfinite(a)) for a in weights + biases):
        raise ValueError(f"{path}: neural_soft weights have inconsistent or non-finite layers")
    return net, meta
