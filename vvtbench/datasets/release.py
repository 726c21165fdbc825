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
  byte for byte: every file present with its sha256, none extra;
* :func:`compare_rebuild` (``vvtbench release verify REBUILD --against COPY``) checks a
  rebuild value by value against a copy of the frozen files (which must verify byte for byte):
  each sample with :func:`vvtbench.samples.compare.compare_samples`, within the release's
  ``[tolerances]`` (:meth:`Release.tolerances`).

A copy of the frozen files matches them byte for byte. A rebuild draws the same instances on
every machine, and matches the frozen files byte for byte only where the floating-point
arithmetic is the same (the CPU's BLAS kernels, the library versions of the release's lock
file ``releases/<name>.lock``); elsewhere it matches them value by value within the
tolerances (docs/dataset.md, "Same answer on every machine").
"""

from __future__ import annotations

import json
import os
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from ..samples.reader import sha256_file as _sha256

__all__ = ["RELEASES_DIR", "RebuildComparison", "Release", "ReleaseError", "build_sums",
           "check_environment_file", "compare_rebuild", "environment_differences", "file_sums",
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
    environment: str | None = None
    environment_sha256: str | None = None
    tolerance_table: dict = field(default_factory=dict)

    @property
    def sums_path(self) -> Path:
        """The frozen file list beside the definition."""
        return self.source.with_suffix(".sha256")

    @property
    def environment_path(self) -> Path | None:
        """The lock file of the environment the release was built in (beside the definition),
        or None when the definition names none."""
        return None if self.environment is None else self.source.parent / self.environment

    def tolerances(self):
        """The :class:`vvtbench.samples.compare.Tolerances` a rebuild is held to: the
        definition's ``[tolerances]`` over the defaults."""
        from dataclasses import replace

        from ..samples.compare import TOLERANCES

        return replace(TOLERANCES, **self.tolerance_table)

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
    from ..samples.compare import TOLERANCES

    tolerances = doc.get("tolerances") or {}
    known = TOLERANCES.to_dict()
    for key, value in tolerances.items() if isinstance(tolerances, dict) else [(None, None)]:
        if key not in known or isinstance(value, bool) or not isinstance(value, int | float) \
                or not value >= 0 or (isinstance(known[key], int) and not isinstance(value, int)):
            raise ReleaseError(f"{path}: key 'tolerances.{key}': allowed keys "
                               f"{', '.join(known)}, each a number >= 0 (dn: an integer)")
    environment = doc.get("environment")
    if environment is not None and (not isinstance(environment, str) or "/" in environment
                                    or environment.startswith(".")):
        raise ReleaseError(f"{path}: key 'environment': the name of a lock file beside the "
                           "definition")
    if len({p.name for p in parts}) != len(parts):
        raise ReleaseError(f"{path}: key 'parts': part names must be unique")
    return Release(name=need(doc, "name", str, ""), vvtbench=need(doc, "vvtbench", str, ""),
                   description=str(doc.get("description", "")),
                   license=str(doc.get("license", "")),
                   observation=dict(doc.get("observation") or {}), parts=tuple(parts),
                   files_sha256=doc.get("files_sha256"), source=path,
                   extra={k: v for k, v in doc.items() if k not in (
                       "name", "vvtbench", "description", "license", "observation", "parts",
                       "files_sha256", "environment", "environment_sha256", "tolerances")},
                   environment=environment,
                   environment_sha256=doc.get("environment_sha256"),
                   tolerance_table=dict(tolerances))


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


def environment_differences(lock: Path) -> list[str]:
    """``name version (lock: version)`` for each package the lock file ``lock`` pins
    (``name==version`` lines) that this Python has at another version or not at all."""
    from importlib import metadata

    out = []
    for line in Path(lock).read_text().splitlines():
        name, sep, version = line.split("#")[0].strip().partition("==")
        if not sep:
            continue
        try:
            have = metadata.version(name.strip())
        except metadata.PackageNotFoundError:
            have = None
        if have != version.strip():
            out.append(f"{name.strip()} {have or 'not installed'} (lock: {version.strip()})")
    return out


def check_environment_file(rel: Release) -> None:
    """ReleaseError when the definition names a lock file that is missing or not the one its
    ``environment_sha256`` records."""
    path = rel.environment_path
    if path is None:
        return
    if not path.is_file():
        raise ReleaseError(f"{rel.source}: key 'environment': no file {path}")
    if rel.environment_sha256 and _sha256(path) != rel.environment_sha256:
        raise ReleaseError(f"{path}: its sha256 is not the environment_sha256 recorded in "
                           f"{rel.source} (the lock file was edited)")


def list_digest(path: Path) -> str:
    """The sha256 of a frozen file list (recorded in the release definition)."""
    return _sha256(path)


@dataclass
class RebuildComparison:
    """What :func:`compare_rebuild` found."""

    problems: list[str] = field(default_factory=list)
    samples: int = 0
    byte_identical: int = 0
    """Samples whose manifest (and so every file) is the frozen one."""
    within: int = 0
    """Samples whose bytes differ and whose values agree within the tolerances."""
    worst: dict[str, float] = field(default_factory=dict)
    """The largest difference per compared item over every sample."""
    flipped: int = 0
    """Modes of opposite sign, over every sample."""

    def summary(self) -> str:
        floats = [v for k, v in self.worst.items() if not k.endswith(" (DN)")]
        dn = [v for k, v in self.worst.items() if k.endswith(" (DN)")]
        text = (f"{self.samples} samples: {self.byte_identical} byte for byte, {self.within} "
                f"within the tolerances, {self.samples - self.byte_identical - self.within} "
                "not")
        if floats:
            text += f"; largest relative difference {max(floats):.1e}"
        if dn:
            text += f", largest image difference {max(dn):g} DN"
        if self.flipped:
            text += f"; {self.flipped} mode(s) of opposite sign"
        return text


def compare_rebuild(rebuilt: str | Path, reference: str | Path, expected: dict[str, str],
                    tolerances=None, progress: Callable[[str], None] | None = None
                    ) -> RebuildComparison:
    """The rebuild ``rebuilt`` against ``reference``, a copy of the frozen files (check it with
    :func:`verify_copy` first), for every entry of the frozen list ``expected``: a sample by
    its values (:func:`vvtbench.samples.compare.compare_samples`, ``tolerances`` or the
    defaults; byte for byte when its manifest is the frozen one), any other file by its
    bytes. ``progress`` is called with each sample folder."""
    from ..samples.compare import TOLERANCES, compare_samples
    from ..samples.reader import DatasetError, open_sample

    tol = TOLERANCES if tolerances is None else tolerances
    rebuilt, reference = Path(rebuilt), Path(reference)
    out = RebuildComparison()
    for rel, digest in expected.items():
        if not rel.endswith("/manifest.json"):
            f = rebuilt / rel
            if not f.is_file() or f.is_symlink():
                out.problems.append(f"{rel}: missing from the rebuild")
            elif _sha256(f) != digest:
                out.problems.append(f"{rel}: differs (compared byte for byte)")
            continue
        folder = rel[: -len("/manifest.json")]
        out.samples += 1
        if progress:
            progress(folder)
        if not (rebuilt / rel).is_file():
            out.problems.append(f"{folder}: missing from the rebuild")
            continue
        if _sha256(rebuilt / rel) == digest:
            try:
                damaged = open_sample(rebuilt / folder, verify=False).verify()
            except DatasetError as error:
                damaged = [str(error)]
            out.problems += [f"{folder}/{p}" for p in damaged]
            out.byte_identical += not damaged
            continue
        c = compare_samples(reference / folder, rebuilt / folder, tol, verify=("rebuilt",))
        out.problems += [f"{folder}/{p}" for p in c.problems]
        out.within += c.ok
        out.flipped += len(c.flipped)
        for k, v in c.worst.items():
            out.worst[k] = max(out.worst.get(k, 0.0), v)
    return out
