"""torchcodec on PyAV's bundled FFmpeg (training/decoding.py): the links carry the names torchcodec asks for, a
process started with them decodes with torchcodec on PyAV's libraries (not the system's), and the training
commands restart themselves that way only where torchcodec finds no FFmpeg."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from fractions import Fraction

import av
import numpy as np
import pytest

from vla_ladder.cli import main
from vla_ladder.training import decoding


def test_links_name_pyav_ffmpeg_as_torchcodec_asks(tmp_path):
    libs = decoding.pyav_libraries()
    assert libs is not None, "the PyAV wheel bundles its FFmpeg under av.libs"
    links = decoding.ffmpeg_links(libs, tmp_path)
    for name, (major, *_) in av.library_versions.items():
        target = (links / f"{name}.so.{major}").resolve()
        assert target.parent == libs.resolve() and target.name.startswith(f"{name}-"), target
    assert decoding.ffmpeg_links(libs, tmp_path) == links  # built once
    assert [p.name for p in tmp_path.iterdir()] == [links.name]  # no half-built directory left


def _video(path, frames: np.ndarray) -> None:
    with av.open(str(path), "w") as out:
        stream = out.add_stream("h264", 20, options={"crf": "10", "g": "2"})
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        stream.time_base = Fraction(1, 20)
        for i, frame in enumerate(frames):
            vf = av.VideoFrame.from_ndarray(frame, format="rgb24")
            vf.pts = i
            out.mux(stream.encode(vf))
        out.mux(stream.encode())


DECODE = """
import json, sys, numpy as np
from lerobot.datasets.video_utils import decode_video_frames
frame = decode_video_frames(sys.argv[1], [0.25], 1e-4, "torchcodec")[0]
np.save(sys.argv[2], (frame.numpy() * 255).round().astype(np.uint8))
maps = open("/proc/self/maps").read().splitlines()
print(json.dumps(sorted({line.split()[-1] for line in maps if "libavcodec" in line})))
"""


def test_torchcodec_decodes_on_pyav_ffmpeg(tmp_path):
    ramp = np.linspace(0, 255, 64, dtype=np.float32)
    frames = np.stack([np.stack(np.broadcast_arrays(ramp[:, None], ramp[None, :], np.full((64, 64), 16.0 * i)), -1)
                       for i in range(8)]).astype(np.uint8)
    _video(tmp_path / "v.mp4", frames)
    env = decoding.torchcodec_env(tmp_path / "cache")
    run = subprocess.run([sys.executable, "-c", DECODE, str(tmp_path / "v.mp4"), str(tmp_path / "f.npy")], env=env,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    loaded = json.loads(run.stdout.strip().splitlines()[-1])  # the libavcodec files mapped into that process
    assert loaded and all(str(decoding.pyav_libraries().resolve()) in p for p in loaded), loaded
    decoded = np.load(tmp_path / "f.npy").transpose(1, 2, 0).astype(float)
    assert np.abs(decoded - frames[5]).mean() < 3, "torchcodec did not return frame 5 (t = 0.25 s)"


def test_training_commands_restart_only_where_torchcodec_has_no_ffmpeg(tmp_path, monkeypatch, capsys):
    class Restarted(Exception):
        pass

    calls = []

    def execve(path, args, env):
        calls.append((path, args, env))
        raise Restarted

    monkeypatch.setattr(os, "execve", execve)
    monkeypatch.setenv("VLA_LADDER_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv(decoding.RESTARTED, raising=False)
    monkeypatch.setattr(decoding, "torchcodec_loads", lambda: False)
    argv = ["study", "micro", "--out", str(tmp_path / "study")]
    with pytest.raises(Restarted):
        main(argv)
    (path, args, env), = calls
    assert path == sys.executable and args == [sys.executable, "-m", "vla_ladder.cli", *argv]
    assert env["LD_LIBRARY_PATH"].split(os.pathsep)[:2] == [
        str(decoding.ffmpeg_links(decoding.pyav_libraries(), tmp_path / "cache")), str(decoding.pyav_libraries())]
    assert env[decoding.RESTARTED] == "1" and "restarting with PyAV's own FFmpeg" in capsys.readouterr().err
    assert not (tmp_path / "study").exists(), "the study started before restarting"

    def unwritable(libs, root):
        raise PermissionError(13, "Permission denied", str(root))

    with monkeypatch.context() as m:  # links that cannot be made: a speed-up missed, the command goes on with PyAV
        m.setattr(decoding, "ffmpeg_links", unwritable)
        decoding.restart_with_torchcodec(argv)
    assert len(calls) == 1 and "LeRobot decodes with PyAV" in capsys.readouterr().err

    monkeypatch.setenv(decoding.RESTARTED, "1")  # the restarted process goes on, whatever torchcodec does
    decoding.restart_with_torchcodec(argv)
    monkeypatch.delenv(decoding.RESTARTED)
    monkeypatch.setattr(decoding, "torchcodec_loads", lambda: True)  # FFmpeg found: nothing to do
    decoding.restart_with_torchcodec(argv)
    assert len(calls) == 1
    monkeypatch.setattr(decoding, "torchcodec_loads", lambda: False)
    assert main(["placements", "--n", "1", "--json", str(tmp_path / "p.json")]) == 0
    assert len(calls) == 1  # commands that decode no video never restart
