"""``rlu validate``: every check a stored dataset must pass, each problem named with its file.

Checks: manifest fields, files inside the folder and their sizes, the segment index (all done by
:func:`~rlu.data.store.open_dataset`), sha256 of every file, schema against the task registry, step
flags (RLDS; stored as bytes 0 or 1), discounts, actions inside the action space, stored episode
returns against the rewards, NaN / inf in float columns, and every compressed frame inflating to
exactly one frame; attachments (the behaviour policies under ``policies/``) by size and sha256 and,
for each policy's ``.npz``, that it holds what the ``.json`` beside it declares and loads without
pickle. Whatever sampling could trip on, validate reports first.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.foreign import MAX_POLICY_BYTES, NpzFile, iter_blocks
from rlu.data.store import (
    FLAG_COLUMNS,
    Dataset,
    ZlibColumn,
    is_attachment,
    open_dataset,
    read_manifest,
    verify_checksums,
)
from rlu.data.store.schema import action_problem
from rlu.domains import DOMAINS
from rlu.files import Int, ListOf, MapOf, Record, Str, read_json
from rlu.types import BoundedSpec, FormatError, RluError, observation_spec_to_json

_CHUNK = 1 << 20  # steps per chunk when scanning columns


@dataclass
class Report:
    path: Path
    problems: list[str] = field(default_factory=list)
    checked: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    """Facts worth knowing that are not problems (release data as recorded)."""

    @property
    def ok(self) -> bool:
        return not self.problems

    def add(self, msg: str) -> None:
        self.problems.append(msg)


def validate(path: str | Path, checksums: bool = True) -> Report:
    path = Path(path)
    report = Report(path)
    try:
        manifest = read_manifest(path)
        ds = open_dataset(path)
    except RluError as e:
        report.add(str(e))
        return report
    report.checked.append("manifest, files, sizes and segment index")
    if checksums:
        for p in verify_checksums(path, manifest):
            report.add(f"{p}: sha256 differs from the manifest (corrupt file)")
        report.checked.append("sha256 of every file")
    for check in (_check_task, _check_flags, _check_actions, _check_returns, _check_finite):
        try:
            check(ds, report)
        except RluError as e:
            report.add(str(e))
    _check_frames(ds, report)
    _check_attachments(ds, manifest, report)
    return report


def _check_attachments(ds: Dataset, manifest: dict, report: Report) -> None:
    """Behaviour policies (``policies/**.npz`` + ``.json``): each ``.npz`` holds exactly the
    arrays its JSON's ``arrays`` field declares (names, shapes, dtypes; checked from the headers
    before a byte is inflated) and each inflates to them without pickle (read in bounded
    blocks, so a member that inflates to gigabytes costs one block)."""
    rels = sorted(r for r in manifest["files"] if is_attachment(r))
    if not rels:
        return
    bad = len(report.problems)
    for rel in rels:
        if not rel.endswith(".npz"):
            continue
        jrel = rel.removesuffix(".npz") + ".json"
        if jrel not in manifest["files"]:
            report.add(f"{ds.path / rel}: no {Path(rel).stem}.json beside it (the policy's config)")
            continue
        try:
            _check_npz_against_json(ds.path / rel, ds.path / jrel)
        except RluError as e:
            report.add(str(e))
    if len(report.problems) == bad:
        report.checked.append(
            f"{len(rels)} attached file(s) under policies/ (each .npz as its .json declares, "
            "loading without pickle)"
        )


MAX_ATTACHMENT_JSON_BYTES = 1 << 20
_ARRAYS = Record(
    {
        "arrays": MapOf(
            Record({"shape": ListOf(Int(0), max_len=8), "dtype": Str(max_len=16)}), max_len=256
        )
    }
)
"""What validate reads of a policy's ``.json``: the arrays its ``.npz`` holds (the whole file's
shape is rlu.generate.policies.POLICY_SHAPE, checked when a policy is loaded)."""


def _check_npz_against_json(npz: Path, jpath: Path) -> None:
    fix = "re-generate the dataset"
    declared = read_json(jpath, _ARRAYS, fix, max_bytes=MAX_ATTACHMENT_JSON_BYTES)["arrays"]
    with NpzFile(npz, "a plain-array .npz is what rlu generate writes: " + fix) as z:
        if set(z.infos) != set(declared):
            raise FormatError(
                f"{npz}: arrays {sorted(z.infos)[:8]} differ from {jpath.name}'s field 'arrays' "
                f"{sorted(declared)[:8]}; {fix}"
            )
        for key in sorted(declared):
            m, want = z.member(key), declared[key]
            if list(m.shape) != want["shape"] or m.dtype.name != want["dtype"]:
                raise FormatError(
                    f"{npz}: array {key!r} is {m.dtype}{list(m.shape)}; {jpath.name} field "
                    f"'arrays.{key}' says {want['dtype']}{want['shape']}; {fix}"
                )
        size = sum(z.member(key).nbytes for key in declared)
        if size > MAX_POLICY_BYTES:
            raise FormatError(
                f"{npz}: its arrays declare {size} bytes, more than a kept policy may hold "
                f"({MAX_POLICY_BYTES}); {fix}"
            )
        for key in sorted(declared):
            col = z.column(key)
            for a, b in iter_blocks(col.shape[0] if col.shape else 1, col.row_bytes):
                col.rows(a, b)  # inflated and dropped: the zip's CRC is checked at the end


def _check_task(ds: Dataset, report: Report) -> None:
    task_id = ds.schema.task_id
    if not task_id:
        return
    from rlu.data.store import Schema
    from rlu.tasks import TASKS, rwrl_observation_spec

    task = TASKS.get(task_id)
    if task is None:
        report.add(f"{ds.path / 'manifest.json'}: schema.task_id {task_id!r} is not a known task")
        return
    allowed = [Schema.for_task(task).to_json()]
    if DOMAINS[task.domain].challenges:
        allowed.append(
            Schema.for_task(task, observation=rwrl_observation_spec(task, "easy")).to_json()
        )
    if DOMAINS[task.domain].stacked_frames:  # the release's transition files store whole stacks
        allowed.append(Schema(task.observation_spec, task.action_spec, 1, "raw", task.id).to_json())
    mine = ds.schema.to_json()
    keys = ("observation", "action")
    if not any(all(_norm(mine[k]) == _norm(a[k]) for k in keys) for a in allowed):
        report.add(
            f"{ds.path / 'manifest.json'}: schema does not match task {task_id}: stored "
            f"observation {observation_spec_to_json(ds.schema.observation)} / action "
            f"{mine['action']}; the task wants {allowed[0]['observation']} / {allowed[0]['action']}"
        )
    report.checked.append(f"schema matches task {task_id}")


def _norm(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _norm(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_norm(v) for v in x]
    return x


def _check_flags(ds: Dataset, report: Report) -> None:
    for name in FLAG_COLUMNS:  # a bool column is bytes: 2 or 255 would read as True, unequal to it
        raw = np.asarray(ds.column(name)).view(np.uint8)
        if (raw > 1).any():
            i = int(np.flatnonzero(raw > 1)[0])
            report.add(
                f"{ds.path / 'steps' / name}.bin: step {i} holds byte {raw[i]}; flags are 0/1"
            )
            return
    first = np.asarray(ds.column("is_first"))
    last = np.asarray(ds.column("is_last"))
    term = np.asarray(ds.column("is_terminal"))
    disc = np.asarray(ds.column("discount"))
    start = np.asarray(ds.start)
    end = start + np.asarray(ds.length) - 1
    f = ds.path / "steps"
    if (np.asarray(ds.length) < 1).any():
        report.add(f"{ds.path / 'segments/length.bin'}: a segment has no steps")
        return
    inner_first = first.copy()
    inner_first[start] = False
    if inner_first.any():
        i = int(np.flatnonzero(inner_first)[0])
        report.add(
            f"{f / 'is_first.bin'}: step {i} has is_first inside a segment (only step 0 may)"
        )
    inner_last = last.copy()
    inner_last[end] = False
    if inner_last.any():
        i = int(np.flatnonzero(inner_last)[0])
        report.add(f"{f / 'is_last.bin'}: step {i} has is_last before its segment's end")
    bad = term & ~last
    if bad.any():
        report.add(
            f"{f / 'is_terminal.bin'}: step {int(np.flatnonzero(bad)[0])} is terminal, not last"
        )
    # the transition into a terminal final step has discount 0
    ends_terminal = term[end]
    has_prev = np.asarray(ds.length) >= 2
    sel = end[ends_terminal & has_prev] - 1
    if sel.size and (disc[sel] != 0).any():
        i = int(sel[np.flatnonzero(disc[sel] != 0)[0]])
        report.add(
            f"{f / 'discount.bin'}: step {i} leads into a terminal state but has discount != 0"
        )
    # inside a segment, a discount of 0 must be followed by the episode's end
    zero = np.flatnonzero(disc == 0)
    if zero.size:
        seg = np.searchsorted(start, zero, side="right") - 1
        bad_zero = zero[(zero < end[seg]) & ~(term[end[seg]] & (zero + 1 == end[seg]))]
        if bad_zero.size:
            report.add(
                f"{f / 'discount.bin'}: step {int(bad_zero[0])} has discount 0 but its episode "
                "goes on"
            )
    if ((disc < 0) | (disc > 1)).any():
        report.add(f"{f / 'discount.bin'}: discounts outside [0, 1]")
    report.checked.append("step flags and discounts")


def _check_actions(ds: Dataset, report: Report) -> None:
    """Every action that is taken (not a final step's placeholder) lies in the action space.

    One exception: continuous actions of data converted from the original release are kept as
    recorded, and the environments clip them (MuJoCo clamps controls to their range); those
    outside the bounds are noted, not failed. Discrete actions out of range always fail (an
    agent would index past its Q-values).
    """
    action = ds.column("action")
    last = np.asarray(ds.column("is_last"))
    as_recorded = (
        isinstance(ds.schema.action, BoundedSpec)
        and ds.manifest["provenance"].get("source") == "rl_unplugged release"
    )
    noted = False
    for a in range(0, len(action), _CHUNK):
        block = np.asarray(action[a : a + _CHUNK])
        live = np.flatnonzero(~last[a : a + _CHUNK])
        bad = action_problem(ds.schema.action, block[live])
        if bad is None:
            continue
        msg = f"{ds.path / 'steps/action.bin'}: step {a + int(live[bad[0]])}: {bad[1]}"
        if not (as_recorded and np.isfinite(block[live]).all()):
            report.add(msg)
            return
        if not noted:
            report.notes.append(f"{msg} (as recorded in the release; the env clips actions)")
            noted = True
    report.checked.append("actions inside the action space")


def _check_frames(ds: Dataset, report: Report) -> None:
    """Every frame of a compressed column inflates to exactly one frame (what sampling does)."""
    specs = {**ds.schema.step_columns(), **ds.schema.frame_columns()}
    for name in specs:
        try:
            col = ds.column(name)
            if not isinstance(col, ZlibColumn):
                continue
            for a in range(0, len(col), 4096):
                col.take(np.arange(a, min(a + 4096, len(col))))
        except RluError as e:
            report.add(str(e))
            return
        report.checked.append(f"every frame of {name} inflates")


def _check_returns(ds: Dataset, report: Report) -> None:
    stored = np.asarray(ds.metadata("episode_return"), np.float64)
    if not ds.num_segments:
        return
    sums = np.add.reduceat(np.asarray(ds.column("reward"), np.float64), np.asarray(ds.start))
    has = ~np.isnan(stored)
    first = np.asarray(ds.column("is_first"))[ds.start]
    last = np.asarray(ds.column("is_last"))[np.asarray(ds.start) + np.asarray(ds.length) - 1]
    whole = has & first & last
    tol = 1e-3 * np.maximum(1.0, np.abs(stored))
    bad = np.flatnonzero(whole & (np.abs(sums - np.where(has, stored, 0)) > tol))
    if bad.size:
        i = int(bad[0])
        report.add(
            f"{ds.path / 'segments/meta_episode_return.bin'}: segment {i} stores return "
            f"{stored[i]:.6g} but its rewards ({ds.path / 'steps/reward.bin'}) sum to {sums[i]:.6g}"
        )
    report.checked.append(f"episode returns of {int(whole.sum())} whole episodes")


def _check_finite(ds: Dataset, report: Report) -> None:
    specs = {**ds.schema.step_columns(), **ds.schema.frame_columns()}
    for name, spec in specs.items():
        if not np.issubdtype(np.dtype(spec.dtype), np.floating):
            continue
        col = ds.column(name)
        if isinstance(col, ZlibColumn):
            continue
        for a in range(0, len(col), _CHUNK):
            block = np.asarray(col[a : a + _CHUNK])
            ok = np.isfinite(block)
            if not ok.all():
                row = a + int(np.flatnonzero(~ok.reshape(len(block), -1).all(axis=1))[0])
                report.add(f"{ds.path / 'steps' / name}.bin: NaN or inf at step {row}")
                break
    report.checked.append("no NaN / inf in float columns")
