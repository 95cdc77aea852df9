"""Finding network weights: explicit path, ``DHPTAM_WEIGHTS_DIR``, the user cache, download.

:func:`resolve` looks for a weight file in this order and returns the first hit:

1. an explicit path given by the caller (it must exist: a wrong path is an error, never
   silently replaced by another file);
2. ``$DHPTAM_WEIGHTS_DIR/<file name>``;
3. the user cache, ``$DHPTAM_CACHE_DIR`` or ``$XDG_CACHE_HOME/dhptam/weights`` or
   ``~/.cache/dhptam/weights``, ``/<file name>``;
4. a download from the official URL into the cache, accepted only when its SHA-256 equals the
   pinned one (written to a temporary file in the cache folder and renamed into place, so an
   interrupted or corrupt download never leaves a file under the final name).

Downloads are off when ``DHPTAM_OFFLINE=1`` (or ``download=False``). Offline, or when the file
has no verified checksum, a missing file raises :class:`~dhptam.errors.FileError` naming the
places where it may be put and the URL to fetch it from.

Third-party weights are never shipped with dhptam (see ``docs/FEATURES.md`` for the licences):
R2D2's are CC BY-NC-SA 3.0, SuperPoint's are under Magic Leap's non-commercial licence.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import tempfile
import types
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import FileError, InputError

__all__ = [
    "WEIGHTS",
    "WeightFile",
    "cache_dir",
    "download",
    "resolve",
    "safe_torch_load",
    "sha256_of",
]


@dataclass(frozen=True)
class WeightFile:
    """A published weight file: its name, where it comes from, and its SHA-256 when verified."""

    file_name: str
    url: str
    #: Hex SHA-256 of the official file, or None when it could not be verified (no download then).
    sha256: str | None
    licence: str


_R2D2_URL = "https://github.com/naver/r2d2/raw/master/models/"

#: Known weight files, by extractor-facing name.
WEIGHTS: dict[str, WeightFile] = {
    # SHA-256 of the official files, computed from the copies in ../shared/models/r2d2.
    "r2d2_WASF_N16": WeightFile(
        "r2d2_WASF_N16.pt",
        _R2D2_URL + "r2d2_WASF_N16.pt",
        "9ae90e02a9a133d100ca7aeaa32f4d4d7736a6dd222a530a25c8f7da5e508528",
        "CC BY-NC-SA 3.0 (NAVER Corp.)",
    ),
    "faster2d2_WASF_N16": WeightFile(
        "faster2d2_WASF_N16.pt",
        _R2D2_URL + "faster2d2_WASF_N16.pt",
        "217daa3a166bfe9bf2b68c05c1607a09dd4d552ae1bbeda885479d504eefc14b",
        "CC BY-NC-SA 3.0 (NAVER Corp.)",
    ),
    # The SuperPoint checkpoint could not be fetched to verify its hash when this was written
    # (no copy in ../shared, no network access to the device either), so none is pinned and
    # dhptam will not download it: place the file yourself (the error says where).
    "superpoint_v1": WeightFile(
        "superpoint_v1.pth",
        "https://github.com/magicleap/SuperPointPretrainedNetwork/raw/master/superpoint_v1.pth",
        None,
        "Magic Leap SuperPoint licence (non-commercial research use only)",
    ),
}


def cache_dir() -> Path:
    """The user cache folder for weights (it need not exist yet)."""
    explicit = os.environ.get("DHPTAM_CACHE_DIR")
    if explicit:
        return Path(explicit)
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg else Path.home() / ".cache"
    return base / "dhptam" / "weights"


def sha256_of(path: Path) -> str:
    """Hex SHA-256 of a file, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _where_to_put(spec: WeightFile) -> str:
    weights_dir = os.environ.get("DHPTAM_WEIGHTS_DIR")
    places = ["pass its path explicitly (weights=...)"]
    if weights_dir:
        places.append(f"put it at {Path(weights_dir) / spec.file_name} (DHPTAM_WEIGHTS_DIR)")
    else:
        places.append(f"put it in the folder named by DHPTAM_WEIGHTS_DIR as {spec.file_name}")
    places.append(f"or put it at {cache_dir() / spec.file_name} (the cache)")
    return "; ".join(places)


def resolve(
    name: str,
    explicit: str | os.PathLike[str] | None = None,
    *,
    download: bool | None = None,
    registry: dict[str, WeightFile] | None = None,
) -> Path:
    """Path of the weight file ``name`` (a key of :data:`WEIGHTS`), found or downloaded.

    ``download`` None means "unless ``DHPTAM_OFFLINE=1``". ``registry`` replaces
    :data:`WEIGHTS` (tests point it at a local server).
    """
    if explicit is not None:
        path = Path(explicit).expanduser()
        if not path.is_file():
            raise FileError(
                f"weights: {path} does not exist or is not a file", field="weights", path=str(path)
            )
        return path
    specs = WEIGHTS if registry is None else registry
    if name not in specs:
        raise InputError(
            f"weights: expected one of {sorted(specs)} or a file path, got {name!r}", field="weights"
        )
    spec = specs[name]
    weights_dir = os.environ.get("DHPTAM_WEIGHTS_DIR")
    if weights_dir and (Path(weights_dir) / spec.file_name).is_file():
        return Path(weights_dir) / spec.file_name
    cached = cache_dir() / spec.file_name
    if cached.is_file():
        return cached
    if download is None:
        download = os.environ.get("DHPTAM_OFFLINE", "") not in ("1", "true", "yes")
    if not download:
        raise FileError(
            f"{spec.file_name} ({spec.licence}) is not available and downloads are off (DHPTAM_OFFLINE): "
            f"download it from {spec.url} and {_where_to_put(spec)}",
            field="weights",
            path=str(cached),
        )
    if spec.sha256 is None:
        raise FileError(
            f"{spec.file_name} ({spec.licence}) is not available and dhptam has no verified checksum to "
            f"download it safely: download it from {spec.url} and {_where_to_put(spec)}",
            field="weights",
            path=str(cached),
        )
    return download_file(spec, cached.parent)


def download_file(spec: WeightFile, folder: Path, *, timeout_s: float = 60.0) -> Path:
    """Downloads ``spec`` into ``folder`` atomically, checking its SHA-256; returns the path.

    The bytes go to a temporary file in ``folder`` that is renamed to ``spec.file_name`` only
    after the checksum matched; on any failure the temporary file is removed.
    """
    if spec.sha256 is None:
        raise FileError(f"{spec.file_name}: no verified SHA-256 pinned, refusing to download", path=spec.url)
    folder.mkdir(parents=True, exist_ok=True)
    final = folder / spec.file_name
    digest = hashlib.sha256()
    fd, tmp_name = tempfile.mkstemp(prefix=f".{spec.file_name}.", suffix=".part", dir=folder)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as out:
            try:
                with urllib.request.urlopen(spec.url, timeout=timeout_s) as response:
                    for block in iter(lambda: response.read(1 << 20), b""):
                        digest.update(block)
                        out.write(block)
            except (urllib.error.URLError, OSError, ValueError) as e:
                raise FileError(
                    f"{spec.file_name}: download from {spec.url} failed ({e}); if this machine is offline, "
                    f"download it elsewhere and {_where_to_put(spec)}",
                    field="weights",
                    path=str(final),
                ) from e
        got = digest.hexdigest()
        if got != spec.sha256:
            raise FileError(
                f"{spec.file_name}: SHA-256 of the download from {spec.url} is {got}, "
                f"expected {spec.sha256}; the file was discarded",
                field="weights",
                path=str(final),
            )
        os.replace(tmp, final)
    finally:
        tmp.unlink(missing_ok=True)
    return final


def download(name: str, folder: str | os.PathLike[str] | None = None) -> Path:
    """Downloads the known weight file ``name`` into ``folder`` (default: the cache)."""
    if name not in WEIGHTS:
        raise InputError(f"name: expected one of {sorted(WEIGHTS)}, got {name!r}", field="name")
    return download_file(WEIGHTS[name], Path(folder) if folder is not None else cache_dir())


# --- loading checkpoints without executing pickled code ---------------------------------------

# Globals an R2D2 or SuperPoint checkpoint may name: containers and torch's tensor rebuilders.
# (torch maps storage classes itself before asking the unpickler.)
_ALLOWED_GLOBALS = {
    ("collections", "OrderedDict"),
    ("collections", "defaultdict"),
    ("builtins", "list"),
    ("__builtin__", "list"),
    ("builtins", "dict"),
    ("__builtin__", "dict"),
    ("torch._utils", "_rebuild_tensor_v2"),
    ("torch._utils", "_rebuild_parameter"),
}


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in _ALLOWED_GLOBALS:
            raise pickle.UnpicklingError(f"global {module}.{name} is not allowed in a weight file")
        return super().find_class(module, name)


def _restricted_load(file: Any, **kwargs: Any) -> Any:
    return _RestrictedUnpickler(file, **kwargs).load()


_RESTRICTED_PICKLE = types.ModuleType("dhptam_restricted_pickle")
_RESTRICTED_PICKLE.Unpickler = _RestrictedUnpickler  # type: ignore[attr-defined]
_RESTRICTED_PICKLE.load = _restricted_load  # type: ignore[attr-defined]


def safe_torch_load(path: Path, what: str) -> Any:
    """A checkpoint's contents on the CPU, with no pickled code run.

    torch's own ``weights_only`` loader is tried first; the official R2D2 files are in torch's
    legacy format with a ``defaultdict`` of training losses, which it refuses, so they are read
    through an unpickler that allows only the containers and tensor rebuilders listed above.
    """
    from .base import import_torch

    torch = import_torch()
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError as e:
        raise FileError(f"{path}: {what} checkpoint not found", path=str(path)) from e
    except pickle.UnpicklingError:
        pass
    except Exception as e:  # torch raises several exception types for files it cannot read
        raise FileError(f"{path}: cannot read the {what} checkpoint ({e})", path=str(path)) from e
    try:
        return torch.load(path, map_location="cpu", weights_only=False, pickle_module=_RESTRICTED_PICKLE)
    except Exception as e:
        raise FileError(f"{path}: cannot read the {what} checkpoint ({e})", path=str(path)) from e
