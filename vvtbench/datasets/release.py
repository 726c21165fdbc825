"""Frozen dataset releases: a definition in the repository, a build, and a byte-for-byte check.

A release is a TOML file in ``releases/`` (``releases/vvtbench-v1.toml``)::

    name = "vvtbench-v1"
    vvtbench = "0.1.0"                 # the version that built it
    description = "..."
    license = "CC-BY-4.0"
    [observation]                      # how its problems are observed (what loaders use)
    n_modes = 10
    [[parts]]
    name = "cube_defects-modes"        # a part can be built alone (--part)
    family = "cube_defects"            # a shipped family (scenes/families)
    video = false                      # modes-only instances (no rendering)
    splits = { train = 1000, val = 100, test = 100 }

Instance ``i`` of a split is drawn from a seed derived from (family, split, i) alone
(:func:`vvtbench.scene.families.instance_seed`), so the definition fixes every instance. Its files
are fixed by ``releases/<name>.sha256`` (``sha256  relative/path`` per line, as ``sha256sum``
writes it), recorded from the build the release was frozen from: each sample folder by the
sha256 of its ``manifest.json``, which lists the sha256 of every file in it, so one line fixes
a sample byte for byte; the TOML records the sha256 of that list (``files_sha256``).

* :func:`load_release` reads and checks a definition;
* ``vvtbench release build NAME -o DIR`` generates every part (resumable: finished instances
  are kept; ``--workers``, ``--scheduler`` as for ``generate``) and writes ``DIR/SHA256SUMS``,
  listing only the files the build wrote (:func:`build_sums`); DIR must be new, empty or a
  build of the same release (:func:`vvtbench.io.outputs.claim_output`);
* :func:`verify_copy` (``vvtbench release verify DIR``) checks a copy against the frozen list
  byte for byte: every file present with its sha256, none extra.

A rebuild on another machine, or with another number of workers, draws the same instances and
matches the frozen files to floating-point rounding (eigen-solves use threaded BLAS), not byte
for byte; a copy of the frozen files matches exactly.
"""

from __future__ import annotations

import json
import os
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from ..samples.reader import sha256_file as _sha256

__all__ = ["RELEASES_DIR", "Release", "ReleaseError", "build_sums", "file_sums",
           "is_earlier_build", "load_release", "read_sums", "release_sums", "verify_copy",
           "write_sums"]

_PACKAGE_DIR = Path(__file__).resolve().parent.parent
RELEASES_DIR = next((d for d in (_PACKAGE_DIR / "releases", _PACKAGE_DIR.parent / "releases")
                     if d.is_dir()), _PACKAGE_DIR.parent / "releases")
"""The shipped release definitions: inside the installed package (a wheel), else the source
checkout's top-level ``releases/``."""
SUMS = "SHA256SUMS"
DEFINITION = "release.toml"  # the definition a build was made from (not a release file)
_SPLITS = ("train", "val", "test")


class ReleaseError(ValueError):
    """A release definition, list or copy that cannot be used; the message names the file."""


@dataclass(frozen=True)
class Part:
    name: str
    family: str
    video: bool
    splits: dict[str, int]


@dataclass(frozen=True)
class Release:
    name: str
    vvtbench: str
    description: str
    license: str
    observation: dict
    parts: tuple[Part, ...]
    files_sha256: str | None
    source: Path
    extra: dict = field(default_factory=dict)

    @property
    def sums_path(self) -> Path:
        """The frozen file list beside the definition."""
        return self.source.with_suffix(".sha256")

    def part(self, name: str) -> Part:
        for p in self.parts:
            if p.name == name:
                return p
        raise ReleaseError(f"{self.source}: no part {name!r}; parts: "
                           f"{', '.join(p.name for p in self.parts)}")

    def n_instances(self) -> int:
        return sum(sum(p.splits.values()) for p in self.parts)


def find_release(name_or_path: str | Path) -> Path:
    path = Path(name_or_path)
    if path.suffix == ".toml" and path.is_file():
        return path
    shipped = RELEASES_DIR / f"{name_or_path}.toml"
    if shipped.is_file():
        return shipped
    known = sorted(p.stem for p in RELEASES_DIR.glob("*.toml")) if RELEASES_DIR.is_dir() else []
    raise ReleaseError(f"{name_or_path}: no such release; shipped: {', '.join(known) or 'none'}")


def load_release(name_or_path: str | Path) -> Release:
    """The release definition ``name_or_path`` (a shipped name or a .toml path), checked."""
    from ..scene.families import list_families

    path = find_release(name_or_path)
    try:
        doc = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise ReleaseError(f"{path}: cannot read: {error}") from None

    def need(d: dict, key: str, kind: type, where: str):
        if not isinstance(d.get(key), kind) or isinstance(d.get(key), bool) != (kind is bool):
            raise ReleaseError(f"{path}: key {where}{key!r} must be a {kind.__name__}")
        return d[key]

    parts = []
    families = set(list_families())
    for i, p in enumerate(doc.get("parts") or []):
        where = f"parts[{i}]."
        family = need(p, "family", str, where)
        if family not in families:
            raise ReleaseError(f"{path}: key {where}family: {family!r} is not a shipped family "
                               f"({', '.join(sorted(families))})")
        splits = need(p, "splits", dict, where)
        for s, n in splits.items():
            if s not in _SPLITS or not isinstance(n, int) or isinstance(n, bool) or n < 1:
                raise ReleaseError(f"{path}: key {where}splits.{s}: allowed splits "
                                   f"{', '.join(_SPLITS)} with a count >= 1")
        parts.append(Part(need(p, "name", str, where), family, need(p, "video", bool, where),
                          dict(splits)))
    if not parts:
        raise ReleaseError(f"{path}: key 'parts': a release needs at least one part")
    if len({p.name for p in parts}) != len(parts):
        raise ReleaseError(f"{path}: key 'parts': part names must be unique")
    return Release(name=need(doc, "name", str, ""), vvtbench=need(doc, "vvtbench", str, ""),
                   description=str(doc.get("description", "")),
                   license=str(doc.get("license", "")),
                   observation=dict(doc.get("observation") or {}), parts=tuple(parts),
                   files_sha256=doc.get("files_sha256"), source=path,
                   extra={k: v for k, v in doc.items() if k not in (
                       "name", "vvtbench", "description", "license", "observation", "parts",
                       "files_sha256")})


def _files(root: Path, exclude: tuple[str, ...] = (SUMS, DEFINITION)) -> Iterator[Path]:
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for name in sorted(filenames):
            if not name.startswith(".") and not (dirpath == str(root) and name in exclude):
                yield Path(dirpath) / name


def file_sums(root: str | Path, progress: Callable[[int], None] | None = None,
              exclude: tuple[str, ...] = (SUMS, DEFINITION)) -> dict[str, str]:
    """``{relative POSIX path: sha256}`` of every file under ``root`` (hidden files and the
    root's files named in ``exclude`` -- by default ``SHA256SUMS`` and ``release.toml`` --
    excepted), in path order; symbolic links are refused."""
    root = Path(root)
    out = {}
    for n, f in enumerate(_files(root, exclude)):
        if f.is_symlink():
            raise ReleaseError(f"{f}: a symbolic link (a release holds files only)")
        out[f.relative_to(root).as_posix()] = _sha256(f)
        if progress:
            progress(n + 1)
    return out


def write_sums(sums: dict[str, str], path: Path) -> None:
    """``sha256  path`` lines (``sha256sum -c`` reads them), written atomically."""
    from ..io.files import write_text

    write_text(path, "".join(f"{h}  {p}\n" for p, h in sums.items()))


def read_sums(path: Path) -> dict[str, str]:
    """A ``sha256  path`` list."""
    out = {}
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as error:
        raise ReleaseError(f"{path}: cannot read: {error.strerror}") from None
    for i, line in enumerate(lines, 1):
        digest, sep, rel = line.partition("  ")
        if not sep or len(digest) != 64 or rel.startswith("/") or ".." in rel.split("/"):
            raise ReleaseError(f"{path}: line {i}: expected 'SHA256  relative/path'")
        out[rel] = digest
    return out


def _sample_manifest(path: Path) -> dict[str, str] | None:
    """``{file: sha256}`` of a sample folder's ``manifest.json`` (``{"files": {name:
    {"sha256": ...}}}``), or None when ``path`` is not one."""
    try:
        doc = json.loads(path.read_text())
        files = doc["files"]
        return {str(k): str(v["sha256"]) for k, v in files.items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def release_sums(root: str | Path) -> dict[str, str]:
    """The frozen list of a build: every sample folder by the sha256 of its ``manifest.json``
    (which holds the sha256 of each of its files, checked here), every other file by its own.
    A sample whose files disagree with its manifest is refused."""
    root = Path(root)
    sums = file_sums(root)
    samples = {k[: -len("/manifest.json")] for k in sums if k.endswith("/manifest.json")
               and _sample_manifest(root / k) is not None}
    out = {}
    for rel, digest in sums.items():
        owner = next((s for s in _prefixes(rel) if s in samples), None)
        if owner is None or rel == f"{owner}/manifest.json":
            out[rel] = digest
            continue
        listed = _sample_manifest(root / owner / "manifest.json")
        if listed.get(rel[len(owner) + 1:]) != digest:
            raise ReleaseError(f"{root / rel}: not the file its sample's manifest.json lists")
    return out


def build_sums(root: str | Path, release: Release) -> dict[str, str]:
    """``{relative POSIX path: sha256}`` of the files a build of ``release`` wrote under
    ``root``: for every instance of every part and split found there, its sample's
    ``manifest.json`` and each file that manifest lists -- never another file the folder holds
    (the user's notes, a foreign ``SHA256SUMS``). A listed file that is missing, a link or not
    a regular file is refused."""
    from ..scene.families import load_family

    root = Path(root)
    out: dict[str, str] = {}
    for part in release.parts:
        family = load_family(part.family).name
        for split, n in part.splits.items():
            folder = root / part.name / split
            if folder.is_symlink() or not folder.is_dir():
                continue
            for i in range(n):
                sample = folder / f"{family}-{split}-{i:05d}"
                manifest = sample / "manifest.json"
                if sample.is_symlink() or manifest.is_symlink() or not manifest.is_file():
                    continue
                listed = _sample_manifest(manifest)
                if listed is None:
                    raise ReleaseError(f"{manifest}: not a sample manifest (no 'files')")
                for name in ("manifest.json", *listed):
                    f = sample / name
                    if Path(name).is_absolute() or ".." in Path(name).parts:
                        raise ReleaseError(f"{manifest}: lists {name!r}, not a file inside "
                                           "the sample")
                    if f.is_symlink() or not f.is_file():
                        raise ReleaseError(f"{f}: listed by its sample's manifest.json but "
                                           "missing or not a regular file")
                    out[f.relative_to(root).as_posix()] = _sha256(f)
    return dict(sorted(out.items()))


def is_earlier_build(root: str | Path, release: Release) -> bool:
    """Whether ``root`` is a build of ``release`` made before output folders were marked: its
    ``release.toml`` names the release, and it holds nothing but that, ``SHA256SUMS`` and the
    release's part folders (hidden files aside)."""
    root = Path(root)
    definition = root / DEFINITION
    if definition.is_symlink() or not definition.is_file():
        return False
    try:
        name = tomllib.loads(definition.read_text()).get("name")
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False
    own = {DEFINITION, SUMS, *(p.name for p in release.parts)}
    return name == release.name and all(
        p.name in own for p in root.iterdir() if not p.name.startswith("."))


def _prefixes(rel: str) -> list[str]:
    parts = rel.split("/")
    return ["/".join(parts[:i]) for i in range(len(parts) - 1, 0, -1)]


def verify_copy(root: str | Path, expected: dict[str, str],
                exclude: tuple[str, ...] = (SUMS, DEFINITION)) -> list[str]:
    """Problems of the copy ``root`` against the frozen list ``expected`` (a sample folder
    listed by its ``manifest.json``: every file the manifest lists): missing, changed and extra
    files (empty when the copy matches byte for byte)."""
    root = Path(root)
    problems = []
    found = {f.relative_to(root).as_posix() for f in _files(root, exclude)}
    known = set()

    def check(rel: str, digest: str) -> bool:
        f = root / rel
        known.add(rel)
        if rel not in found:
            problems.append(f"{rel}: missing")
        elif f.is_symlink() or not f.is_file():
            problems.append(f"{rel}: not a regular file")
        elif _sha256(f) != digest:
            problems.append(f"{rel}: sha256 differs (changed or damaged)")
        else:
            return True
        return False

    for rel, digest in expected.items():
        if check(rel, digest) and rel.endswith("/manifest.json"):
            listed = _sample_manifest(root / rel)
            folder = rel[: -len("manifest.json")]
            for name, sha in (listed or {}).items():
                check(folder + name, sha)
    problems += [f"{rel}: not in the release" for rel in sorted(found - known)]
    return problems


def list_digest(path: Path) -> str:
    """The sha256 of a frozen file list (recorded in the release definition)."""
    return _sha256(path)
