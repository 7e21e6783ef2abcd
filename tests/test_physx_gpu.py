"""physx_cuda asked for without SAPIEN's PhysX GPU library: found, fetchable, or one line saying where it goes."""

import functools
import http.server
import socket
import threading

import pytest

from vla_ladder.task.physx_gpu import check_physx_gpu, library


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_absent_library_is_found_fetched_or_refused_with_its_place(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    path, release = library()
    assert path.parent.parent == tmp_path / "home" / ".sapien" / "physx" and release.endswith(".zip")

    # Absent and unreachable: one line naming the file, the folder it goes in, and the CPU alternative.
    unreachable = f"http://127.0.0.1:{_closed_port()}/linux-so.zip"
    with pytest.raises(ValueError) as e:
        check_physx_gpu(timeout_s=2, url=unreachable)
    message = str(e.value)
    assert str(path) in message and f"unzip it into {path.parent}" in message and "physx_cpu" in message
    assert "\n" not in message

    # Absent but the release answers: SAPIEN will download it on first use.
    (tmp_path / "www").mkdir()
    (tmp_path / "www" / "linux-so.zip").write_bytes(b"PK")
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path / "www"))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        assert check_physx_gpu(url=f"http://127.0.0.1:{server.server_port}/linux-so.zip") == path
        with pytest.raises(ValueError, match="HTTP 404"):  # a release that does not exist
            check_physx_gpu(url=f"http://127.0.0.1:{server.server_port}/nothing.zip")
    finally:
        server.shutdown()

    # On disk: no network needed.
    path.parent.mkdir(parents=True)
    path.write_bytes(b"")
    assert check_physx_gpu(url=unreachable) == path
