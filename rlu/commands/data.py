"""``rlu validate``, ``rlu export`` and ``rlu import``."""

from __future__ import annotations

import argparse

_DATASET_HELP = (
    "the dataset: a folder, or a name as rlu.load_dataset takes it (a task id: the bundled or "
    "converted release data; a TFDS name)"
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("validate", help="check a stored dataset; exit code 1 on any problem")
    p.add_argument("path", help=_DATASET_HELP)
    p.add_argument("--no-checksums", action="store_true", help="skip the sha256 of every file")
    p.set_defaults(func=_validate)

    p = sub.add_parser("export", help="export a stored dataset to another format")
    p.add_argument("path", help=_DATASET_HELP)
    p.add_argument("--format", required=True, choices=["d4rl", "d3rlpy", "minari"])
    p.add_argument(
        "-o",
        "--out",
        help="d4rl: output file, X.hdf5 (D4RL's HDF5 layout) or X.npz (numpy); d3rlpy: X.h5, "
        "the file d3rlpy's ReplayBuffer.dump writes (ReplayBuffer.load reads it)",
    )
    p.add_argument(
        "--id",
        help="Minari dataset id NAMESPACE/NAME-vN (minari; default for a dataset imported from "
        "Minari: its own id)",
    )
    p.add_argument(
        "--minari-dir",
        help="Minari datasets directory (default: $MINARI_DATASETS_PATH or ~/.minari/datasets)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing -o file, if rlu wrote it (a file another tool wrote is never "
        "replaced)",
    )
    p.set_defaults(func=_export)

    p = sub.add_parser("import", help="import a dataset of another format into the store")
    p.add_argument(
        "src",
        help="d4rl: .npz or .hdf5 file; d3rlpy: the .h5 of MDPDataset.dump; minari: a dataset id "
        "or directory",
    )
    p.add_argument("--format", required=True, choices=["d4rl", "d3rlpy", "minari"])
    p.add_argument(
        "--task",
        help="task id, e.g. control_suite/cartpole_swingup (d4rl and d3rlpy: required unless "
        "the file is an export of rlu's; minari: default, the schema of the dataset's spaces)",
    )
    p.add_argument("--out", required=True, help="new dataset directory")
    p.add_argument("--minari-dir", help="Minari datasets directory, for a dataset id (minari)")
    p.set_defaults(func=_import)


def _validate(args: argparse.Namespace) -> int:
    import os

    from rlu.data import load_dataset
    from rlu.data.validate import validate

    # a folder is validated as it is (problems reported, not raised); a name is resolved first
    path = args.path if os.path.exists(args.path) else str(load_dataset(args.path).path)
    report = validate(path, checksums=not args.no_checksums)
    for c in report.checked:
        print(f"ok   {c}")
    for n in report.notes:
        print(f"note {n}")
    for p in report.problems:
        print(f"FAIL {p}")
    print(f"{args.path}: {'valid' if report.ok else f'{len(report.problems)} problem(s)'}")
    return 0 if report.ok else 1


def _note(line: str) -> None:
    print(f"note: {line}")


def _export(args: argparse.Namespace) -> int:
    from rlu.data import load_dataset
    from rlu.types import RluError

    ds = load_dataset(args.path)
    if args.format == "d4rl":
        if args.out is None:
            raise RluError("--format d4rl needs -o/--out FILE.hdf5 (or FILE.npz)")
        from rlu.data.d4rl import export_d4rl

        out = export_d4rl(ds, args.out, overwrite=args.overwrite, note=_note)
    elif args.format == "d3rlpy":
        if args.out is None:
            raise RluError("--format d3rlpy needs -o/--out FILE.h5")
        from rlu.data.d3rlpy_io import export_d3rlpy

        out = export_d3rlpy(ds, args.out, overwrite=args.overwrite, note=_note)
    else:
        if args.out is not None:
            raise RluError("--format minari writes a Minari dataset: give --id (and --minari-dir)")
        from rlu.data.minari import export_minari

        out = export_minari(ds, args.id, root=args.minari_dir, note=_note)
    print(f"wrote {out}")
    return 0


def _import(args: argparse.Namespace) -> int:
    from pathlib import Path

    from rlu.data.store import open_dataset
    from rlu.files import check_output

    inputs = [args.src] if Path(args.src).exists() else []
    if args.format == "minari" and args.minari_dir:
        inputs.append(args.minari_dir)
    check_output(args.out, inputs, what="dataset folder")
    if args.format == "d4rl":
        from rlu.data.d4rl import import_d4rl

        dest = import_d4rl(args.src, args.out, args.task)
    elif args.format == "d3rlpy":
        from rlu.data.d3rlpy_io import import_d3rlpy

        dest = import_d3rlpy(args.src, args.out, args.task)
    else:
        from rlu.data.minari import import_minari

        dest = import_minari(args.src, args.out, args.task, root=args.minari_dir)
    ds = open_dataset(dest)
    print(f"wrote {dest}: {len(ds)} episodes, {ds.num_steps} steps")
    return 0
