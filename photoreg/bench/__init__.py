"""Benchmarks: `photoreg bench speed` (per-stage ms on a recording), `photoreg bench sweep` (speed against
error), `photoreg bench renderers` (shadow renderers side by side), and `photoreg score` (accuracy against ground truth)."""


def bench_command(args) -> int:
    """CLI entry of `photoreg bench KIND`: the kind's module does the work."""
    if args.bench_kind == "renderers":
        from .renderers import renderers_command
        return renderers_command(args)
    if args.bench_kind == "sweep":
        from .sweep import sweep_command
        return sweep_command(args)
    from .speed import speed_command
    return speed_command(args)
