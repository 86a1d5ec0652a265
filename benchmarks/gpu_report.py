"""Writes benchmarks/gpu.md from the JSON that benchmarks/gpu_run.sh left in benchmarks/results/."""
import glob
import json
from pathlib import Path

HERE = Path(__file__).resolve().parent
STAGES = ["preprocess", "fuse", "raycast", "sample", "transfer", "solve", "total"]


def main() -> None:
    runs = [json.loads(Path(f).read_text()) for f in sorted(glob.glob(str(HERE / "results" / "speed_*.json")))]
    runs.sort(key=lambda r: (r["stride"], -r["rays"]))
    c = json.loads((HERE / "results" / "cuda_check.json").read_text())
    r0 = runs[0]
    rows = [f"| {r['stride']} | {r['rays']} | {r['bands']} | {r['frames_per_s']:.1f} | "
            + " | ".join(f"{r['ms_mean'].get(k, 0.0):.1f}" for k in STAGES) + " |" for r in runs]
    (HERE / "gpu.md").write_text(f"""# GPU figures

Device: **{r0['device_name']}** (driver 580.159.04), Warp {r0['warp']}, Open3D {r0['open3d']} (CUDA build);
fusion ran on the GPU (`{r0['fusion_on']}`). Recording: the first 30 frames of TUM fr1_rpy ({r0['size']}, real
Kinect), {r0['voxel_size'] * 100:.0f} cm voxels, {r0['ray_length']} m rays; 3 warm-up frames left out, {r0['frames_timed']} timed.

Reproduce on a GPU machine with warp-lang 1.19.0 and open3d 0.20.0 (CUDA build) installed:
`bash benchmarks/gpu_run.sh RECORDING benchmarks/results && python benchmarks/gpu_report.py`.

## CUDA agrees with the CPU (same frames, same settings)
`benchmarks/cuda_check.py` on {c['frames']} frames: SH relative difference at most {c['sh_rel_diff_max']:.4f}, dominant
direction difference at most {c['direction_diff_deg_max']:.2f} deg, Warp ray-cast depth within 1 cm on
{c['raycast_depth_within_1cm']:.1%} of the pixels valid in both ({c['valid_cpu']} CPU / {c['valid_gpu']} GPU).

## Full per-frame pipeline (fuse, ray cast, R_TR, solve), ms per stage, mean
| stride | rays | bands | frames/s | {' | '.join(STAGES)} |
|---|---|---|---|{'---|' * len(STAGES)}
""" + "\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
