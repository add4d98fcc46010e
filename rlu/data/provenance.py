"""Where a dataset's steps came from, in the few fields a reported number carries.

A score beside the paper's must say what data produced it (the paper's agents learned from the
release's files). :func:`data_source` reads a manifest's provenance, as each writer of rlu records
it (``rlu convert``, ``rlu generate``, the imports, the synthetic writer), into::

    {"source": "release" | "generated" | "imported" | "synthetic" | "unknown",
     "family": ..., "files": ...,       # release: the family and how many of its files,
     "shards": {"used": k, "of": n},    #   k of the n release shards of its dataset
     "scale": ..., "command": ...,      # generated: the recipe's scale and the command
     "format": ...,                     # imported: d4rl, d3rlpy or minari
     "steps": ...}                      # every source: the dataset's steps (its manifest)

A report checks ``shards`` against the paper's condition "every release shard of the task"
(``rlu.report.conditions``): a shard counts when its file name is one of the
registry's names for the task's dataset (``rlu.tasks.ReleaseDataset.shard_names``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

IMPORT_FORMATS = ("d4rl", "d3rlpy", "minari")


def data_source(manifest: Mapping[str, Any]) -> dict[str, Any]:
    """The data-source summary of a dataset's manifest (see the module docstring)."""
    out = _source(manifest.get("provenance") or {})
    counts = manifest.get("counts")
    steps = counts.get("steps") if isinstance(counts, Mapping) else None
    if isinstance(steps, int) and not isinstance(steps, bool):
        out["steps"] = steps
    return out


def release_shards(provenance: Mapping[str, Any]) -> dict[str, Any] | None:
    """``{"used": k, "of": n, "dataset": binding}``: how many of the release's n shards of the
    dataset a converted release dataset holds (its files matched by name against the
    registry's; ``of`` None where no file has a release shard's name), or None when the
    provenance names no known task and family."""
    from rlu.tasks import get_task
    from rlu.types import RluError

    names = {str(f.get("name")) for f in provenance.get("files") or [] if isinstance(f, Mapping)}
    try:
        release = get_task(str(provenance.get("task"))).release_dataset(
            str(provenance.get("family"))
        )
    except RluError:
        return None
    best: dict[str, Any] | None = None
    for binding, n in release.shards.items():
        used = len(names & {s.rsplit("/", 1)[-1] for s in release.shard_names(binding)})
        if used and (best is None or used > best["used"]):
            best = {"used": used, "of": int(n), "dataset": binding}
    return best or {"used": 0, "of": None, "dataset": None}


def _source(prov: Any) -> dict[str, Any]:
    if not isinstance(prov, Mapping):
        return {"source": "unknown"}
    source = prov.get("source")
    if source == "rl_unplugged release":
        out: dict[str, Any] = {"source": "release", "family": str(prov.get("family"))}
        if isinstance(prov.get("files"), list):
            out["files"] = len(prov["files"])
            shards = release_shards(prov)
            if shards is not None:
                out["shards"] = shards
        for key in ("run", "challenge"):
            if prov.get(key) is not None:
                out[key] = prov[key]
        return out
    if prov.get("generator") == "rlu generate":
        settings: Mapping[str, Any] = (
            prov["settings"] if isinstance(prov.get("settings"), Mapping) else {}
        )
        out = {"source": "generated", "command": str(prov.get("command", ""))}
        if settings.get("scale") is not None:
            out["scale"] = str(settings["scale"])
        return out
    if source in IMPORT_FORMATS:
        return {"source": "imported", "format": source}
    if source == "synthetic":
        return {"source": "synthetic"}
    return {"source": "unknown"}
