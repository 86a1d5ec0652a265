"""Train the neural shadow-map U-Net on views written by photoreg.train.shadow_data, export it to ONNX.

Loss per view: the data term, mean over valid pixels and channels of (1 - o (1 - v) - target)^2 (the
ratio the renderer applies, against the voxel renderer's), plus PERTURB_WEIGHT times the perturbation
term, mean over pixels valid in both of (v - v')^2 with v' the output for the same view under a sub-pixel
camera turn and a light turn of up to half a degree (temporal stability, Datta et al. 2022), on the first
PERTURB_SHARE of each batch.
Adam, learning rate decayed by cosine to 5% over the time budget; CPU, `--threads` threads.

    python3 -m photoreg.train.shadow_train TRAIN_DIR --val VAL_DIR --out data/neural_shadowmap --minutes 12
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from photoreg.io.atomic import write_json
from photoreg.train.shadow_data import load_shards
from photoreg.train.shadow_eval import evaluate
from photoreg.train.shadow_unet import ShadowUNet, export_onnx, parameter_count

PERTURB_WEIGHT = 0.5
PERTURB_SHARE = 0.5   # share of each batch whose perturbed twin is evaluated too


def _tensors(views: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    return {"x": torch.from_numpy(views["buffers"]), "xp": torch.from_numpy(views["perturbed"]),
            "t": torch.from_numpy(views["target"]).permute(0, 3, 1, 2).contiguous(),
            "o": torch.from_numpy(views["opacity"]).permute(0, 3, 1, 2).contiguous(),
            "w": torch.from_numpy(views["weight"])[:, None]}


def losses(net: ShadowUNet, b: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """(data term, perturbation term) of a batch (module docstring); the perturbed twins of the first
    PERTURB_SHARE of the batch go through the network with it."""
    n, k = len(b["x"]), max(1, int(len(b["x"]) * PERTURB_SHARE))
    v = net(torch.cat([b["x"], b["xp"][:k]]))
    v, vp = v[:n], v[n:]
    ratio = 1.0 - b["o"] * (1.0 - v)
    w = b["w"]
    data = (w * (ratio - b["t"]) ** 2).sum() / (3.0 * w.sum()).clamp_min(1.0)
    both = w[:k] * (b["xp"][:k, 0:1] > 0)
    perturb = (both * (v[:k] - vp) ** 2).sum() / both.sum().clamp_min(1.0)
    return data, perturb


def predictor(net: ShadowUNet):
    """numpy buffers (N, C, H, W) -> visibility (N, H, W) with the torch network (validation)."""
    def predict(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return np.concatenate([net(torch.from_numpy(x[i:i + 32]))[:, 0].numpy() for i in range(0, len(x), 32)])
    return predict


def train(train_dir: str, val_dir: str | None, out: Path, minutes: float, batch: int, lr: float, seed: int,
          threads: int) -> dict:
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    rng = np.random.default_rng(seed)
    data = load_shards(train_dir)
    val = load_shards(val_dir) if val_dir else None
    T = _tensors(data)
    n = len(T["x"])
    net = ShadowUNet()
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    budget = minutes * 60.0
    t0, step, log = time.perf_counter(), 0, []
    while (elapsed := time.perf_counter() - t0) < budget:
        for g in opt.param_groups:
            g["lr"] = lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * elapsed / budget)))
        idx = torch.from_numpy(rng.choice(n, size=min(batch, n), replace=False))
        b = {k: v[idx] for k, v in T.items()}
        data_l, pert_l = losses(net.train(), b)
        loss = data_l + PERTURB_WEIGHT * pert_l
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        if step % 100 == 0:
            row = {"step": step, "seconds": round(elapsed, 1), "data": float(data_l.detach()), "perturb": float(pert_l.detach())}
            if val is not None and step % 500 == 0:
                row.update(evaluate(val, predictor(net.eval())))
            log.append(row)
            print(json.dumps(row), flush=True)
    seconds = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)
    onnx_path = out / "shadow_unet.onnx"
    export_onnx(net, onnx_path)
    report = {"parameters": parameter_count(net), "onnx_bytes": onnx_path.stat().st_size,
              "train_seconds": round(seconds, 1), "steps": step, "batch": batch, "train_views": n,
              "threads": threads, "lr": lr, "perturb_weight": PERTURB_WEIGHT, "perturb_share": PERTURB_SHARE, "seed": seed}
    if val is not None:
        report["validation"] = evaluate(val, predictor(net.eval()))
    report["log"] = log
    write_json(out / "training.json", report)
    return report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Train the neural shadow-map U-Net (needs the `train` extra: torch).")
    ap.add_argument("train_dir")
    ap.add_argument("--val", help="held-out views folder (validation RMSE in the region of interest)")
    ap.add_argument("--out", default="data/neural_shadowmap")
    ap.add_argument("--minutes", type=float, default=12.0)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    r = train(a.train_dir, a.val, Path(a.out), a.minutes, a.batch, a.lr, a.seed, a.threads)
    print(json.dumps({k: v for k, v in r.items() if k != "log"}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
