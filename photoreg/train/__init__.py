"""Offline training of learned renderers: `photoreg train KIND ...` (KIND: neural_soft)."""
import importlib

# train kind -> "module:function" taking the parsed arguments and returning an exit code
TRAINERS = {"neural_soft": "photoreg.train.neural_soft:train_command"}


def train_command(args) -> int:
    """CLI entry of `photoreg train KIND`: the kind's module does the work."""
    module, func = TRAINERS[args.train_kind].split(":")
    return getattr(importlib.import_module(module), func)(args)
