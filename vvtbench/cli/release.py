"""``vvtbench release``: build a frozen release, verify a copy of it, freeze a build."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from .args import explain, positive_int


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vvtbench release",
                                description="frozen dataset releases (releases/*.toml): build "
                                "one, verify a copy byte for byte, or freeze a build's files")
    sub = p.add_subparsers(dest="action", required=True)
    b = sub.add_parser("build", help="generate every part of a release into a folder "
                       "(resumable) and list its files' sha256 in FOLDER/SHA256SUMS")
    b.add_argument("release", help="a shipped release name (e.g. vvtbench-v1) or its .toml")
    b.add_argument("-o", "--out", required=True, type=Path, help="output folder")
    b.add_argument("--part", action="append", default=None,
                   help="build only this part (repeatable), e.g. the modes-only one")
    b.add_argument("--workers", type=positive_int, default=1, help="local processes")
    b.add_argument("--scheduler", default=None, help="a Dask scheduler address")
    v = sub.add_parser("verify", help="check a copy against the release's frozen file list, "
                       "byte for byte; or, with --against COPY, a rebuild against a copy, "
                       "value by value")
    v.add_argument("folder", type=Path, help="the copy (the folder `build` wrote)")
    v.add_argument("--against", type=Path, default=None, metavar="COPY",
                   help="FOLDER is a rebuild (on this machine): check COPY, a copy of the "
                   "frozen files, byte for byte, then FOLDER against it value by value within "
                   "the release's tolerances (docs/dataset.md, 'Same answer on every "
                   "machine')")
    v.add_argument("--release", default=None,
                   help="the release (default: the one named in FOLDER/release.toml)")
    v.add_argument("--part", action="append", default=None,
                   help="verify only this part's files (repeatable)")
    f = sub.add_parser("freeze", help="record a build's files as the release's frozen list "
                       "(releases/NAME.sha256) and its digest in the definition")
    f.add_argument("folder", type=Path, help="a build (its built parts are frozen)")
    f.add_argument("--release", default=None,
                   help="the definition to freeze (default: the shipped release named in "
                   "FOLDER/release.toml)")
    return p


def main_release(argv: list[str] | None = None, run=None) -> int:
    """``vvtbench release ...``; ``run`` is the ``vvtbench`` command itself (``build`` runs
    ``generate`` through it, with its one-line errors)."""
    args = _parser().parse_args(argv)
    if args.action == "build":
        if run is None:
            raise TypeError("release build runs generate through the vvtbench command: pass run")
        return _build(args, run)
    return {"verify": _verify, "freeze": _freeze}[args.action](args)


def _fail(message) -> int:
    print(f"error: {explain(message)}", file=sys.stderr)
    return 2


def _build(args, main) -> int:
    from ..datasets.release import (
        SUMS,
        ReleaseError,
        build_sums,
        is_earlier_build,
        load_release,
        write_sums,
    )
    from ..io.files import write_text
    from ..io.outputs import OutputError, claim_output
    try:
        rel = load_release(args.release)
        parts = [rel.part(n) for n in args.part] if args.part else list(rel.parts)
        out = claim_output(args.out, "release build",
                           adopt=lambda folder: is_earlier_build(folder, rel))
    except (ReleaseError, OutputError) as error:
        return _fail(error)
    write_text(out / "release.toml", rel.source.read_text())
    _note_environment(rel)
    t0 = time.perf_counter()
    for part in parts:
        for split, n in part.splits.items():
            folder = out / part.name / split
            print(f"{rel.name}: {part.name} {split}: {n} instances of {part.family} -> {folder}",
                  flush=True)
            argv = ["generate", part.family, "--split", split, "--n", str(n), "-o",
                    str(folder), "--workers", str(args.workers), "--no-progress"]
            if not part.video:
                argv.append("--no-video")
            if args.scheduler:
                argv += ["--scheduler", args.scheduler]
            code = main(argv)
            if code != 0:
                print(f"error: {part.name} {split}: generate exited {code}; rerun the same "
                      "command to resume", file=sys.stderr)
                return code
    try:
        sums = build_sums(out, rel)
    except ReleaseError as error:
        return _fail(error)
    write_sums(sums, out / SUMS)
    size = sum((out / p).stat().st_size for p in sums)
    print(f"{rel.name}: {len(sums)} files, {size / 2**20:.1f} MiB in "
          f"{time.perf_counter() - t0:.0f} s -> {out} (list: {out / SUMS}); check a copy with "
          f"`vvtbench release verify {out}`")
    return 0


def _verify(args) -> int:
    from ..datasets.release import (
        ReleaseError,
        check_environment_file,
        list_digest,
        load_release,
        read_sums,
        verify_copy,
    )

    folder = args.folder
    if not folder.is_dir():
        return _fail(f"{folder}: no such folder")
    try:
        rel = load_release(args.release or folder / "release.toml")
        if args.release is None:  # the definition the copy names, and its shipped list
            rel = load_release(rel.name)
        if not rel.sums_path.is_file():
            raise ReleaseError(f"{rel.sums_path}: the release {rel.name} has no frozen file "
                               "list yet (`vvtbench release freeze` a complete build)")
        if rel.files_sha256 and list_digest(rel.sums_path) != rel.files_sha256:
            raise ReleaseError(f"{rel.sums_path}: its sha256 is not the files_sha256 recorded "
                               f"in {rel.source} (the list was edited)")
        check_environment_file(rel)
        expected = read_sums(rel.sums_path)
    except ReleaseError as error:
        return _fail(error)
    frozen = {k.split("/")[0] for k in expected if "/" in k}
    wanted = args.part or [p.name for p in rel.parts if p.name in frozen]
    unfrozen = [p for p in wanted if p not in frozen]
    if unfrozen:
        return _fail(f"{rel.sums_path}: part(s) {', '.join(unfrozen)} have no frozen files yet "
                     f"(frozen: {', '.join(sorted(frozen)) or 'none'})")
    keep = tuple(f"{p}/" for p in wanted)
    if args.part:
        expected = {k: v for k, v in expected.items() if k.startswith(keep)}
    if args.against is not None:
        return _verify_rebuild(args, rel, folder, expected, wanted, keep)
    problems = verify_copy(folder, expected)
    unbuilt = tuple(f"{p.name}/" for p in rel.parts if p.name not in frozen)
    problems = [p for p in problems if not p.startswith(unbuilt)]  # not frozen: not checked
    if args.part:  # the other parts' files are not this check's business
        problems = [p for p in problems if p.startswith(keep)]
    if problems:
        _print_problems(folder, problems, str(rel.sums_path))
        if any(p.endswith("manifest.json: sha256 differs (changed or damaged)")
               for p in problems):
            print(f"(a rebuild rather than a copy? its bytes match only on a machine that "
                  f"rounds alike; compare its values: vvtbench release verify {folder} "
                  "--against COPY, COPY a copy of the frozen files)", file=sys.stderr)
        return 1
    print(f"{folder}: {len(expected)} files of {', '.join(wanted)} match {rel.name} byte for "
          "byte")
    return 0


def _print_problems(folder: Path, problems: list[str], against: str) -> None:
    print(f"{folder}: {len(problems)} problem(s) against {against}", file=sys.stderr)
    for p in problems[:50]:
        print(f"  {p}", file=sys.stderr)
    if len(problems) > 50:
        print(f"  ... and {len(problems) - 50} more", file=sys.stderr)


def _note_environment(rel) -> None:
    """Say on stderr where this Python differs from the release's lock file (a rebuild is then
    expected to match value by value, not byte for byte)."""
    from ..datasets.release import environment_differences

    if rel.environment_path is None or not rel.environment_path.is_file():
        return
    diff = environment_differences(rel.environment_path)
    if diff:
        shown = "; ".join(diff[:5]) + (f"; and {len(diff) - 5} more" if len(diff) > 5 else "")
        print(f"note: this environment differs from {rel.environment_path.name} in "
              f"{len(diff)} package(s): {shown}", file=sys.stderr)


def _verify_rebuild(args, rel, folder: Path, expected: dict, wanted: list, keep: tuple) -> int:
    """``verify FOLDER --against COPY``: COPY byte for byte, then FOLDER value by value."""
    from ..datasets.release import compare_rebuild, verify_copy

    copy = args.against
    if not copy.is_dir():
        return _fail(f"{copy}: no such folder")
    unbuilt = tuple(f"{p.name}/" for p in rel.parts if p.name not in wanted)
    problems = [p for p in verify_copy(copy, expected) if not p.startswith(unbuilt)]
    if args.part:
        problems = [p for p in problems if p.startswith(keep)]
    if problems:
        _print_problems(copy, problems, f"{rel.sums_path} (the copy to compare with must be "
                                        "the frozen files)")
        return 1
    _note_environment(rel)
    tol = rel.tolerances()
    result = compare_rebuild(folder, copy, expected, tol)
    if result.problems:
        _print_problems(folder, result.problems, f"{copy}, value by value ({result.summary()})")
        return 1
    print(f"{folder}: {', '.join(wanted)} match {rel.name} value by value ({result.summary()}; "
          f"tolerances: {', '.join(f'{k} {v:g}' for k, v in tol.to_dict().items())})")
    return 0


def _freeze(args) -> int:
    import tomllib

    from ..datasets.release import ReleaseError, list_digest, load_release, release_sums, write_sums
    from ..io.files import write_text

    try:
        rel = load_release(args.release or load_release(args.folder / "release.toml").name)
    except ReleaseError as error:
        return _fail(error)
    try:
        sums = release_sums(args.folder)
    except ReleaseError as error:
        return _fail(error)
    built = {"/".join(k.split("/")[:2]) for k in sums}
    frozen = [p.name for p in rel.parts if all(f"{p.name}/{s}" in built for s in p.splits)]
    partial = [p.name for p in rel.parts if p.name not in frozen
               and any(k.startswith(f"{p.name}/") for k in built)]
    if not frozen or partial:
        return _fail(f"{args.folder}: no complete part" if not frozen else
                     f"{args.folder}: parts {', '.join(partial)} are only partly built")
    sums = {k: v for k, v in sums.items() if k.split("/")[0] in frozen or "/" not in k}
    write_sums(sums, rel.sums_path)
    text = rel.source.read_text()
    digest = list_digest(rel.sums_path)
    lines = [ln for ln in text.splitlines() if not ln.startswith("files_sha256")]
    head = [i for i, ln in enumerate(lines) if ln.startswith("vvtbench")]
    at = head[0] + 1 if head else 0
    lines.insert(at, f'files_sha256 = "{digest}"   # sha256 of {rel.sums_path.name}')
    write_text(rel.source, "\n".join(lines) + "\n")
    tomllib.loads(rel.source.read_text())
    print(f"{rel.name}: {len(sums)} files of {', '.join(frozen)} frozen in {rel.sums_path}")
    return 0
