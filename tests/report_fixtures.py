"""Constructed run directories (the `vla-ladder eval --out DIR` contract) for statistics/report tests.

The episodes are made up, so the tests know every count; the files are written exactly as the runner
writes them (episodes.parquet, summary.json, config.json, videos/*.mp4).
"""

from __future__ import annotations

import json
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pandas as pd

from vla_ladder.conditions import Condition
from vla_ladder.evaluation.metrics import summarize
from vla_ladder.files import write_json, write_parquet
from vla_ladder.task.layouts import sample_layout


def episode_row(policy: str, regime: str, split: str, k: int, j: int, seed: int, kind: str,
                video: str = "") -> dict:
    lay = sample_layout(Condition(regime, split, k), seed)
    other = lay.objects[1] if k > 1 else "none"
    held = {"success": lay.target, "wrong_object": other}.get(kind, "none")
    return {"policy": policy, "regime": regime, "split": split, "num_objects": k, "episode": j, "seed": seed,
            "target": lay.target, "instruction": lay.instruction, "held": held,
            "success": kind == "success", "grasp_any": kind in ("success", "wrong_object", "grasp_lost"),
            "reach": kind in ("success", "reached_no_grasp"), "reach_dist": 0.01 if kind == "success" else 0.2,
            "object_set": "standin", "layout": json.dumps(lay.to_dict()), "video": video}


def write_video(path: Path, steps: int = 50, seed: int = 0) -> None:
    """A small synthetic MP4: a coloured square moving over a gradient, 20 fps like the env."""
    import imageio.v3 as iio
    rng = np.random.default_rng(seed)
    colour = rng.integers(50, 255, 3)
    frames = np.zeros((steps, 64, 128, 3), np.uint8)
    frames[..., 1] = np.linspace(40, 200, 128, dtype=np.uint8)[None, None, :]
    for t in range(steps):
        frames[t, 20:40, 2 * t:2 * t + 20] = colour
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, frames, fps=20, codec="libx264", macro_block_size=16)


def make_run(out: Path, policy: str, conditions: list[tuple[str, str, int]], kinds: list[str], seed: int = 0,
             videos: int = 0) -> Path:
    """One run dir: every condition gets len(kinds) episodes whose outcome kinds are `kinds` (in order);
    the first `videos` episodes of each condition get a synthetic MP4."""
    rows = []
    for regime, split, k in conditions:
        for j, kind in enumerate(kinds):
            video = ""
            if j < videos:
                video = f"videos/{regime}_{split}_{k}_{j:04d}.mp4"
                write_video(out / video, seed=j)
            rows.append(episode_row(policy, regime, split, k, j, seed + j, kind, video))
    df = pd.DataFrame(rows)
    write_parquet(out / "episodes.parquet", df)
    write_json(out / "summary.json", {"policy": {"name": policy}, "provenance": {}, "first_seed": seed,
                                      "episodes_per_condition": len(kinds), "conditions": summarize(df)})
    write_json(out / "config.json", {"policy": policy, "first_seed": seed, "episodes": len(kinds)})
    return out


CHROMIUM = "/usr/bin/chromium"


@contextmanager
def chromium_page(path: Path) -> Iterator[tuple[Any, list[str]]]:
    """`path` opened in headless Chromium (Debian's, as scripts/setup.sh installs it), kept off the network, once
    every image has decoded: yields the playwright page and the URLs of the requests that failed so far."""
    from playwright.sync_api import sync_playwright

    assert Path(CHROMIUM).exists(), "Debian's chromium is missing: scripts/setup.sh installs it"
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=[
            "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync"])
        try:
            tab = browser.new_page(viewport={"width": 1200, "height": 900})
            failed: list[str] = []
            tab.on("requestfailed", lambda r: failed.append(r.url[:80]))
            tab.goto(f"file://{path}")
            tab.wait_for_function("[...document.images].every(i => i.complete)", timeout=30000)
            yield tab, failed
        finally:
            browser.close()


def table_row(tab: Any, table_text: str, row: int = 1) -> dict[str, str]:
    """Row `row` of the first table containing `table_text`, as {header: cell}."""
    head, cells = tab.evaluate("([text, k]) => { const t = [...document.querySelectorAll('table')].find(t => "
                               "t.innerText.includes(text)); return [t.rows[0].innerText, t.rows[k].innerText]; }",
                               [table_text, row])
    return dict(zip(head.split("\t"), cells.split("\t")))


def first_table_row(page: Path, table_text: str) -> tuple[list[int], dict[str, str]]:
    """The natural widths of `page`'s images, and the first data row of its first table containing `table_text`."""
    with chromium_page(page) as (tab, _):
        return tab.evaluate("[...document.images].map(i => i.naturalWidth)"), table_row(tab, table_text)
