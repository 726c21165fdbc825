"""Modes extracted from a sample's video, kept beside the data so learners extract once.

:func:`extracted_modes_folder` extracts on the first call and reuses the folder while the
video's sha256, the options and the extraction revision match; :func:`default_cache_dir`
says where the folders go.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..samples.reader import DatasetError, sha256_file
from .packed import is_dataset

__all__ = ["EXTRACTED_DIR", "default_cache_dir", "extracted_modes_folder", "extraction_key"]

#: Name of the folder (beside the samples or the dataset) that keeps extracted modes.
EXTRACTED_DIR = ".vvtbench-extracted"


def default_cache_dir(path: str | Path) -> Path:
    """Where extracted modes of the samples in ``path`` are kept by default: a
    ``.vvtbench-extracted`` folder in a folder of samples, beside a single sample, and beside
    an exported dataset (in a sub-folder named after it)."""
    path = Path(path)
    if is_dataset(path):
        return path.parent / EXTRACTED_DIR / path.name
    if (path / "truth.json").is_file() and (path / "manifest.json").is_file():
        return path.parent / EXTRACTED_DIR
    return path / EXTRACTED_DIR


def extraction_key(extract: Mapping[str, Any]) -> str:
    """The cache folder name of an extraction: ``<extractor>-r<revision>``, plus the first 12
    hex digits of the sha256 of the other ``extract_modes`` options when any are set."""
    from ..modes.revision import extraction_revision

    opts = dict(extract)
    extractor = opts.pop("extractor", "phase")
    if not isinstance(extractor, str):
        raise DatasetError("extract: extractor must be a name (or module:Class) to be cached")
    revision = extraction_revision(opts)
    rev = "-".join(map(str, revision)) if isinstance(revision, list) else str(revision)
    safe = "".join(ch if ch.isalnum() or ch in "._" else "_" for ch in extractor)
    key = f"{safe}-r{rev}"
    if opts:
        text = json.dumps(opts, sort_keys=True, default=str)
        key += "-" + hashlib.sha256(text.encode()).hexdigest()[:12]
    return key


def _video_sha256(source: Any) -> str:
    info = source.info.get("video") if isinstance(source.info.get("video"), dict) else {}
    entry = source.manifest.get("files", {}).get(str(info.get("file", "")))
    if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
        raise DatasetError(f"{getattr(source, 'path', source)}: manifest.json lists no "
                           "sha256 of the video; regenerate the sample")
    return entry["sha256"]


def _reusable(folder: Path, video_sha: str, extract: dict) -> bool:
    try:
        doc = json.loads((folder / "source.json").read_text())
    except (OSError, ValueError):
        return False
    if (not isinstance(doc, dict) or doc.get("video_sha256") != video_sha
            or doc.get("extract") != json.loads(json.dumps(extract, default=str))):
        return False
    files = doc.get("files")
    if not isinstance(files, dict) or set(files) != {"modes.json", "modes.npz"}:
        return False
    return all((folder / rel).is_file() and sha256_file(folder / rel) == digest
               for rel, digest in files.items())


def extracted_modes_folder(source: Any, name: str, extract: Mapping[str, Any],
                           cache: str | Path) -> Path | None:
    """The folder of the modes extracted from ``source``'s video with ``extract``
    (:func:`vvtbench.modes.extract_modes` options), extracting them on the first call only.

    The folder is ``cache/<extractor>-r<revision>[-<options hash>]/`` (modes.json, modes.npz
    and source.json: the video's sha256, the options and the sha256 of both mode files). It is
    reused while all of them match; otherwise the modes are extracted again and the folder is
    replaced in one rename. Returns None for a dataset entry that was packed with extracted
    modes (observe uses those) and raises :class:`DatasetError` for a sample with no video.
    """
    from ..io.files import write_json
    from ..modes import extract_modes

    packed = getattr(source, "extracted_modes", None)
    if packed is not None and getattr(source, "_extracted", None):
        return None
    if not getattr(source, "has_video", False):
        raise DatasetError(f"{name}: observation 'extracted' needs a video; this sample was "
                           "generated without one (--no-video)")
    extract = dict(extract)
    folder = Path(cache) / extraction_key(extract)
    video_sha = _video_sha256(source)
    if _reusable(folder, video_sha, extract):
        return folder
    video_path = getattr(source, "video_path", None)
    frames = video_path if video_path is not None else source.frames()
    modeset = extract_modes(frames, source.fps, **extract)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = folder.with_name(f".{folder.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
    try:
        modeset.save(tmp)
        write_json(tmp / "source.json", {
            "video_sha256": video_sha, "extract": extract, "instance": name,
            "files": {rel: sha256_file(tmp / rel) for rel in ("modes.json", "modes.npz")}})
        old = folder.with_name(f".{folder.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.old")
        try:
            os.replace(folder, old)  # a stale or damaged extraction
        except FileNotFoundError:
            pass
        try:
            os.replace(tmp, folder)
        except OSError:  # another process put its extraction there first
            if not _reusable(folder, video_sha, extract):
                raise
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder
