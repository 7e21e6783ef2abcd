"""Did two runs of a study make the same thing? Datasets file by file, models by their weights, evaluations episode
by episode.

    .venv/bin/python benchmarks/study_repro.py RUN_A RUN_B [--out benchmarks/results/NAME.json]

RUN_A and RUN_B are `vla-ladder study` directories (the same config, e.g. a preset run twice, or one preset and
a JSON that keeps a part of it). For every dataset, model and evaluation both hold: which files are byte for byte
the same (where one differs: a table's columns, a JSON map's keys or a text's lines; a dataset's provenance rows
and recording state differ in when and from which server each demo came, WHEN_AND_WHERE), whether every weights
file (*.safetensors of the last checkpoint) hashes the same, and in how many episodes success, grasp-any, reach
and the held object agree. Prints a line per item and writes the comparison as JSON.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import tyro

from vla_ladder import files

# What says when and from which server a demo was recorded, not what it holds (docs/recording.md, "Byte for
# byte"): provenance rows' columns and the recording state's key.
WHEN_AND_WHERE = {"server", "recorded_at", "updated"}


@dataclass
class Args:
    """Compare two runs of a study, item by item."""

    run_a: tyro.conf.Positional[Path]
    """a study directory"""
    run_b: tyro.conf.Positional[Path]
    """another run of the same study"""
    out: Path | None = None
    """JSON to write (default: print only)"""
    note: str = ""
    """what the two runs were (code, machine, how they were started), kept in the JSON"""


def _sha(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _tree(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): _sha(p) for p in sorted(root.rglob("*"))
            if p.is_file() and not any(part.startswith(".") for part in p.relative_to(root).parts)}


def what_differs(a: Path, b: Path) -> list[str]:
    """Where two versions of a file differ: a table's columns, a JSON map's keys, a text's lines, else its bytes."""
    if a.suffix == ".parquet":
        ta, tb = pd.read_parquet(a), pd.read_parquet(b)
        if list(ta.columns) == list(tb.columns) and len(ta) == len(tb):
            return [c for c in ta.columns if not ta[c].astype(str).equals(tb[c].astype(str))] or ["bytes"]
    elif a.suffix == ".json":
        ja, jb = json.loads(a.read_text()), json.loads(b.read_text())
        if isinstance(ja, dict) and isinstance(jb, dict):
            return sorted(k for k in ja.keys() | jb.keys() if ja.get(k) != jb.get(k)) or ["bytes"]
    elif a.suffix == ".md":
        la, lb = a.read_text().splitlines(), b.read_text().splitlines()
        return [f"line {i + 1}: {x!r} -> {y!r}" for i, (x, y) in enumerate(zip(la, lb)) if x != y][:5] or ["lines"]
    return ["bytes"]


def compare_dataset(a: Path, b: Path) -> dict:
    ta, tb = _tree(a), _tree(b)
    differ = {k: what_differs(a / k, b / k) for k in sorted(ta.keys() & tb.keys()) if ta[k] != tb[k]}
    return {"files": len(ta.keys() | tb.keys()), "same": len(ta.keys() & tb.keys()) - len(differ),
            "only_in_a": sorted(ta.keys() - tb.keys()), "only_in_b": sorted(tb.keys() - ta.keys()),
            "differ": differ,
            "differ_beyond_when_and_where": sorted(k for k, what in differ.items() if not set(what) <= WHEN_AND_WHERE)}


def compare_model(a: Path, b: Path) -> dict:
    last = Path("checkpoints/last/pretrained_model")
    wa = {p.name: _sha(p) for p in sorted((a / last).glob("*.safetensors"))}
    wb = {p.name: _sha(p) for p in sorted((b / last).glob("*.safetensors"))}
    return {"weights": {k: {"a": wa.get(k), "b": wb.get(k)} for k in sorted(wa.keys() | wb.keys())},
            "identical": bool(wa) and wa == wb}


def compare_eval(a: Path, b: Path) -> dict:
    key = ["regime", "split", "num_objects", "seed"]
    ea = pd.concat([pd.read_parquet(p) for p in sorted(a.rglob("episodes.parquet"))])
    eb = pd.concat([pd.read_parquet(p) for p in sorted(b.rglob("episodes.parquet"))])
    both = ea.merge(eb, on=key, suffixes=("_a", "_b"))
    return {"episodes_a": len(ea), "episodes_b": len(eb), "paired": len(both),
            **{f"same_{m}": int((both[f"{m}_a"] == both[f"{m}_b"]).sum())
               for m in ("success", "grasp_any", "reach", "held")},
            "success_a": int(both["success_a"].sum()), "success_b": int(both["success_b"].sum())}


def main(args: Args) -> dict:
    for run in (args.run_a, args.run_b):
        if not (run / "study.json").is_file():
            raise SystemExit(f"{run} is not a study directory (no study.json)")
    result: dict = {"benchmark": "study_repro", "run_a": str(args.run_a), "run_b": str(args.run_b), "note": args.note,
                    "provenance": files.provenance()}  # (of the comparison; each run's timings.json names its machine)
    for kind, compare in (("data", compare_dataset), ("models", compare_model), ("eval", compare_eval)):
        names = sorted({p.name for p in (args.run_a / kind).glob("[!.]*")}  # (not a recording's .NAME.recording)
                       & {p.name for p in (args.run_b / kind).glob("*")})
        result[kind] = {n: compare(args.run_a / kind / n, args.run_b / kind / n) for n in names}
        for n, r in result[kind].items():
            if kind == "data":
                beyond = {k: r["differ"][k] for k in r["differ_beyond_when_and_where"]}
                print(f"dataset {n}: {r['same']} of {r['files']} files the same, {len(r['differ']) - len(beyond)} "
                      f"differ in when and where only; otherwise: {beyond or 'none'}")
            elif kind == "models":
                print(f"model {n}: weights {'identical' if r['identical'] else 'DIFFER'}")
            else:
                print(f"eval {n}: {r['paired']} episodes paired; the same success in {r['same_success']}, held object "
                      f"in {r['same_held']} (successes {r['success_a']} and {r['success_b']})")
    if args.out:
        files.write_json(args.out, result)
        print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main(tyro.cli(Args))
