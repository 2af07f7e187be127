"""``evdown preprocess``: the command line of :func:`evdown_torch.data.preprocess`.

:func:`add_command` adds the subcommand to the ``evdown`` parser, :func:`run` runs it (also as
one rank of a ``torchrun`` launch: it joins the gloo process group torchrun describes).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from evdown_torch.arguments import (
    Subparsers,
    add_file_format_options,
    add_out_option,
    add_sensor_size_option,
    add_threads_option,
    factor_argument,
    refuse_threshold_flag,
    setting_argument,
)
from evdown_torch.data import shards
from evdown_torch.data.preprocessing import RecordingError, preprocess
from evdown_torch.data.sources import RECORDING_SUFFIXES, open_source
from evdown_torch.distributed import process_group
from evdown_torch.threads import command_threads
from evdown_torch.transforms.registry import METHODS

__all__ = ["add_command", "run"]


def _dataset_name(text: str) -> str:
    if text in ("synthetic", "dvsgesture", "nmnist") or (
            text.startswith("folder:") and len(text) > len("folder:")):
        return text
    raise argparse.ArgumentTypeError(
        f"expected synthetic, dvsgesture, nmnist or folder:PATH, got {text!r}")


def add_command(subparsers: Subparsers) -> None:
    """Register ``evdown preprocess`` on the ``evdown`` subparsers."""
    parser = subparsers.add_parser(
        "preprocess",
        help="downscale every recording of a dataset once into a sharded cache (torchrun-ready)",
        description="Downscale every recording of a dataset once and write .npy shards plus "
        "manifest.json; read them back with evdown_torch.data.PreprocessedDataset. Under "
        "torchrun each rank takes a disjoint share. A rerun resumes.")
    parser.add_argument("--dataset", required=True, type=_dataset_name, metavar="NAME",
                        help="synthetic, dvsgesture, nmnist or folder:PATH (PATH/CLASS/FILE, "
                        f"any format evdown reads: {', '.join(RECORDING_SUFFIXES)})")
    parser.add_argument("--method", required=True, choices=sorted(METHODS), metavar="NAME",
                        help=f"one of {', '.join(sorted(METHODS))}")
    parser.add_argument("--factor", required=True, type=factor_argument, help="F or FX,FY")
    parser.add_argument("--set", type=setting_argument, action="append", metavar="KEY=VALUE",
                        help="a setting of the method, e.g. --set threshold=0.5 (a contrast "
                        "threshold for most methods, the firing threshold for lif)")
    add_out_option(parser, "the cache folder")
    parser.add_argument("--split", choices=("train", "test"), default="train",
                        help="dataset split (synthetic, dvsgesture, nmnist; default train)")
    parser.add_argument("--root", metavar="DIR",
                        help="folder the Tonic dataset lives in (its save_to: DIR/NMNIST/Train/, "
                        "extracted, or DIR/DVSGesture/ibmGestureTrain/); for nmnist also a "
                        "folder in N-MNIST's layout (Train/<digit>/*.bin, Test/...)")
    add_sensor_size_option(parser, "sensor of a folder dataset (required) or of the synthetic "
                           "one")
    add_file_format_options(parser)  # --time-unit, --columns: a folder's files
    parser.add_argument("--samples-per-class", type=int, metavar="N",
                        help="synthetic recordings per class (default 24)")
    parser.add_argument("--duration-us", type=int, metavar="US",
                        help="synthetic recording length, microseconds (default 6000000)")
    parser.add_argument("--seed", type=int, help="synthetic dataset seed (default 0)")
    parser.add_argument("--shard-size", type=int, default=32, metavar="N",
                        help="recordings per shard (default 32)")
    parser.add_argument("--workers", type=int, metavar="N",
                        help="processes working, this one included (default: one per "
                        "core; 1 per rank under torchrun)")
    add_threads_option(parser, "torch threads of each working process (one is never much "
                       "slower per process, and the cores go to the workers)")
    parser.add_argument("--on-error", choices=("skip", "stop"), default="skip",
                        help="a recording that cannot be read: report and skip it (default), "
                        "or stop the run, keeping the complete shards")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--threshold", help=argparse.SUPPRESS)  # gone: explains itself
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run ``evdown preprocess`` (also one rank of a ``torchrun`` launch)."""
    refuse_threshold_flag(args)
    # Ranks finish their shares at different times; the manifest collective waits for them.
    with process_group():
        source = open_source(
            args.dataset, split=args.split, root=args.root,
            sensor_size=tuple(args.sensor_size) if args.sensor_size else None,
            samples_per_class=args.samples_per_class, duration_us=args.duration_us,
            seed=args.seed, time_unit=args.time_unit, columns=args.columns)
        settings = dict(args.set or [])
        try:
            result = preprocess(source, args.out, args.method, args.factor, settings,
                                shard_size=args.shard_size, workers=args.workers,
                                on_error=args.on_error,
                                threads=command_threads(args.threads),
                                progress=False if args.no_progress else None)
        except (RecordingError, OSError) as error:
            raise ValueError(f"{error} (complete shards are kept; a rerun resumes)") from None
    if result.manifest is not None:
        counts = result.manifest["counts"]
        rate = result.recordings / result.seconds if result.seconds > 0 else float("inf")
        print(
            f"{args.method}: {counts['recordings']} recordings in {counts['shards']} shards "
            f"({len(result.kept)} kept from an earlier run), {counts['skipped']} skipped, "
            f"{counts['events_in']} events in, {counts['events_out']} out; "
            f"{result.seconds:.1f} s ({rate:.1f} recordings/s); "
            f"wrote {Path(args.out) / shards.MANIFEST}"
        )
    return 0
