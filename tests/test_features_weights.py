"""Weight resolution: lookup order, checksum-verified downloads from a local server, messages."""

from __future__ import annotations

import hashlib
import http.server
import os
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from conftest import shared_path

from dhptam import features
from dhptam.errors import FileError
from dhptam.features import weights
from dhptam.features.weights import WEIGHTS, WeightFile, resolve, safe_torch_load, sha256_of

PAYLOAD = b"not really a network, but bytes with a known hash\n" * 1000


@pytest.fixture
def server(tmp_path: Path) -> Iterator[str]:
    """A local HTTP server in a thread serving ``tmp_path/served``; yields its base URL."""
    root = tmp_path / "served"
    root.mkdir()
    (root / "net.pt").write_bytes(PAYLOAD)

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def __init__(self, *args: object, **kwargs: object) -> None:
            super().__init__(*args, directory=str(root), **kwargs)  # type: ignore[arg-type]

        def log_message(self, format: str, *args: object) -> None:
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}/"
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join()


@pytest.fixture
def env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    """Private cache and weights folders; downloads allowed."""
    dirs = {"cache": tmp_path / "cache", "weights": tmp_path / "weights"}
    monkeypatch.setenv("DHPTAM_CACHE_DIR", str(dirs["cache"]))
    monkeypatch.delenv("DHPTAM_WEIGHTS_DIR", raising=False)
    monkeypatch.delenv("DHPTAM_OFFLINE", raising=False)
    return dirs


def _registry(url: str, sha256: str | None) -> dict[str, WeightFile]:
    return {"net": WeightFile("net.pt", url, sha256, "test licence")}


def test_the_pinned_r2d2_checksums_are_those_of_the_official_files() -> None:
    for name in ("r2d2_WASF_N16", "faster2d2_WASF_N16"):
        assert sha256_of(shared_path("models", "r2d2", f"{name}.pt")) == WEIGHTS[name].sha256
        assert WEIGHTS[name].url == f"https://github.com/naver/r2d2/raw/master/models/{name}.pt"


def test_download_into_the_cache_checks_the_hash_and_is_reused(server: str, env: dict[str, Path]) -> None:
    registry = _registry(server + "net.pt", hashlib.sha256(PAYLOAD).hexdigest())
    path = resolve("net", registry=registry)
    assert path == env["cache"] / "net.pt"
    assert path.read_bytes() == PAYLOAD
    assert sorted(p.name for p in env["cache"].iterdir()) == ["net.pt"]  # no temporary left
    # Second time: found in the cache, no network needed.
    offline = _registry("http://127.0.0.1:9/unreachable", registry["net"].sha256)
    assert resolve("net", registry=offline) == path


def test_wrong_checksum_leaves_nothing_in_the_cache(server: str, env: dict[str, Path]) -> None:
    registry = _registry(server + "net.pt", "0" * 64)
    with pytest.raises(FileError, match="SHA-256") as info:
        resolve("net", registry=registry)
    assert "discarded" in str(info.value) and hashlib.sha256(PAYLOAD).hexdigest() in str(info.value)
    assert not (env["cache"] / "net.pt").exists()
    assert list(env["cache"].iterdir()) == []


def test_lookup_order_explicit_then_weights_dir_then_cache(
    server: str, env: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    registry = _registry(server + "net.pt", hashlib.sha256(PAYLOAD).hexdigest())
    env["cache"].mkdir()
    (env["cache"] / "net.pt").write_bytes(b"cached")
    assert resolve("net", registry=registry) == env["cache"] / "net.pt"
    env["weights"].mkdir()
    (env["weights"] / "net.pt").write_bytes(b"in weights dir")
    monkeypatch.setenv("DHPTAM_WEIGHTS_DIR", str(env["weights"]))
    assert resolve("net", registry=registry) == env["weights"] / "net.pt"
    explicit = tmp_path / "mine.pt"
    explicit.write_bytes(b"explicit")
    assert resolve("net", explicit, registry=registry) == explicit
    with pytest.raises(FileError, match=r"missing\.pt"):
        resolve("net", tmp_path / "missing.pt", registry=registry)


def test_offline_and_missing_says_where_to_put_the_file(
    env: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("DHPTAM_OFFLINE", "1")
    with pytest.raises(FileError) as info:
        resolve("r2d2_WASF_N16")
    message = str(info.value)
    assert "DHPTAM_OFFLINE" in message
    assert str(env["cache"] / "r2d2_WASF_N16.pt") in message
    assert "DHPTAM_WEIGHTS_DIR" in message
    assert "https://github.com/naver/r2d2/raw/master/models/r2d2_WASF_N16.pt" in message
    with pytest.raises(FileError, match="DHPTAM_OFFLINE"):
        features.load("r2d2", device="cpu")


def test_unreachable_server_says_where_to_put_the_file(env: dict[str, Path]) -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    registry = _registry(f"http://127.0.0.1:{port}/net.pt", "0" * 64)
    with pytest.raises(FileError, match=r"download from .* failed") as info:
        resolve("net", registry=registry)
    assert str(env["cache"] / "net.pt") in str(info.value)
    assert not env["cache"].exists() or list(env["cache"].iterdir()) == []


def test_superpoint_has_no_verified_hash_so_it_is_never_downloaded(env: dict[str, Path]) -> None:
    assert WEIGHTS["superpoint_v1"].sha256 is None
    with pytest.raises(FileError, match="no verified checksum") as info:
        features.load("superpoint", device="cpu")
    assert "superpoint_v1.pth" in str(info.value) and "magicleap" in str(info.value)


def test_known_names_resolve_through_the_weights_dir(
    env: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("DHPTAM_WEIGHTS_DIR", str(shared_path("models", "r2d2")))
    monkeypatch.setenv("DHPTAM_OFFLINE", "1")
    assert "Fast_Quad" in repr(features.load("r2d2", "faster2d2_WASF_N16", device="cpu"))
    assert "Fast_Quad" not in repr(features.load("r2d2", device="cpu"))


class _Payload:
    """Pickles to a call of os.mkdir: what a malicious checkpoint would do."""

    def __init__(self, target: Path) -> None:
        self.target = target

    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (os.mkdir, (str(self.target),))


@pytest.mark.parametrize("legacy", [False, True])
def test_checkpoints_cannot_run_code(tmp_path: Path, legacy: bool) -> None:
    target = tmp_path / "pwned"
    path = tmp_path / "evil.pt"
    torch.save({"state_dict": {}, "net": _Payload(target)}, path, _use_new_zipfile_serialization=not legacy)
    with pytest.raises(FileError, match=r"evil\.pt"):
        safe_torch_load(path, "R2D2")
    assert not target.exists()
    with pytest.raises(FileError):
        features.load("r2d2", path, device="cpu")
    assert not target.exists()


def test_cache_dir_follows_xdg(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("DHPTAM_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert weights.cache_dir() == tmp_path / "dhptam" / "weights"
