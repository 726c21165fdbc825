"""What a record's timing and length allow: the notes ``extract`` prints and modes.json keeps.

* **A decimated record** (a camera file whose frames were stored every ``n``-th of those
  recorded: Photron ``Save Step``, Phantom ``Decimation``): the stored frames sample the
  motion at ``record_fps / n``, so anything above half that rate folds into the band
  (:func:`record_notes`, kind ``"aliasing"``).
* **A rate given against the file's**: ``--fps`` that is not the rate the file states for its
  stored frames (kind ``"fps_mismatch"``; the given rate is used).
* **A short record** (kind ``"short_record"``): fewer than :data:`MIN_FRAMES` frames, or a
  ``fmin`` below the lowest frequency the record can show ``min_bin`` cycles of.
* **The peak picker's frequency floor** (:data:`FREQUENCY_FLOOR_BINS`, applied in
  :func:`.jackknife.peak_uncertainty`).
* **Why no mode was found** (:func:`no_modes_reason`).
"""

from __future__ import annotations

from typing import Any

__all__ = ["FREQUENCY_FLOOR_BINS", "MIN_FRAMES", "no_modes_reason", "ordinal", "record_notes"]

#: fewer frames than this is a short record: under 64 bins up to the Nyquist frequency, fewer
#: than the 65 of the noise floor's running median (half width 32 bins)
MIN_FRAMES = 128

#: the peak picker's frequency standard error is never reported below this fraction of a bin
#: (``fps / n_frames``): its jackknife and parabola bias hold for one stationary line, and an
#: unresolved neighbour or a drifting frequency moves the peak by a tenth of a bin or more
#: without widening the jackknife (docs/modes.md, "Frequency floor")
FREQUENCY_FLOOR_BINS = 0.1


def ordinal(n: int) -> str:
    """``1st``, ``2nd``, ``3rd``, ``100th``."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def record_notes(meta: dict[str, Any], fps: float, n_frames: int, *, average: int = 1,
                 fmin: float | None = None, min_bin: int = 3,
                 fps_source: str = "argument") -> list[dict[str, Any]]:
    """Notes on what the record's timing and length allow, each a dict with ``kind``,
    ``message`` (one line) and the numbers behind it.

    Parameters
    ----------
    meta : the source's metadata (:attr:`.video.VideoStream.meta`): ``frame_rate``,
        ``frame_rate_source``, ``record_fps``, ``decimation``, ``decimation_key`` of a
        camera file.
    fps : the rate of the source's frames used (Hz; given or the file's).
    n_frames : frames in the spectrum (after averaging ``average`` frames into one).
    fmin : the lowest frequency asked for (Hz), or None.
    min_bin : the lowest bin searched (a line needs that many cycles in the record).
    fps_source : ``"argument"`` when ``fps`` was given, else ``"container"``.
    """
    notes: list[dict[str, Any]] = []
    step = int(meta.get("decimation") or 1)
    stated = meta.get("frame_rate")
    if step > 1 and meta.get("record_fps"):
        record = float(_fraction(meta["record_fps"]))
        stored = record / step
        key = meta.get("decimation_key") or "decimation"
        notes.append({
            "kind": "aliasing", "record_fps": record, "decimation": step,
            "stored_fps": stored, "nyquist_hz": stored / 2,
            "message": (
                f"decimated record: recorded at {record:g} fps, every {ordinal(step)} frame "
                f"stored ({key} {step}): {stored:g} fps; motion above {stored / 2:g} Hz (up to "
                f"the camera's {record / 2:g} Hz) folds into 0-{stored / 2:g} Hz (a line at f "
                f"reads at |f - k {stored:g}| Hz) and cannot be told from a mode there")})
    if fps_source == "argument" and stated and meta.get("frame_rate_source") == "file header":
        file_fps = float(_fraction(stated))
        if abs(file_fps - fps) > 1e-9 * file_fps:
            notes.append({
                "kind": "fps_mismatch", "file_fps": file_fps, "given_fps": fps,
                "message": (f"--fps {fps:g} is not the {file_fps:g} fps the file states for "
                            "its stored frames"
                            + (f" (recorded at {float(_fraction(meta['record_fps'])):g} fps, "
                               f"every {ordinal(step)} frame stored)" if step > 1 else "")
                            + f": the frequencies are scaled by {fps / file_fps:.6g}")})
    fps = fps / average
    df = fps / n_frames
    duration = n_frames / fps
    lowest = min_bin * df
    if n_frames < MIN_FRAMES:
        notes.append({
            "kind": "short_record", "n_frames": int(n_frames), "duration_s": duration,
            "bin_hz": df, "min_frames": MIN_FRAMES,
            "message": (f"short record: {n_frames} frames ({duration:.4g} s at {fps:g} fps), "
                        f"bins of {df:.4g} Hz, {n_frames // 2} up to {fps / 2:g} Hz: fewer "
                        f"than {MIN_FRAMES} frames leave the noise floor, the damping and the "
                        "stability check few bins to stand on; record longer")})
    if fmin is not None and fmin < lowest:
        need = min_bin / fmin if fmin > 0 else float("inf")
        notes.append({
            "kind": "short_record", "fmin_hz": float(fmin), "lowest_searched_hz": lowest,
            "duration_s": duration, "cycles": min_bin,
            "message": (f"the record ({duration:.4g} s) holds {min_bin} cycles only above "
                        f"{lowest:.4g} Hz: nothing from --fmin {fmin:g} Hz to {lowest:.4g} Hz "
                        "was searched"
                        + (f"; {need:.4g} s of record reach {fmin:g} Hz" if fmin > 0 else ""))})
    return notes


def _fraction(value: Any) -> Any:
    from fractions import Fraction

    return Fraction(str(value))


def no_modes_reason(meta: dict[str, Any], fps: float, n_frames: int) -> str:
    """Why a mode set holds no mode, in one line, from its metadata: no significant peak in
    the band (and whether the record is short), or every candidate rejected (counted by
    reason)."""
    band = meta.get("band_hz") or [0.0, fps / 2]
    analysed = len(meta.get("roughness") or [])
    rejected = meta.get("rejected") or []
    short = [n for n in meta.get("record_notes") or [] if n.get("kind") == "short_record"]
    if rejected:
        counts: dict[str, int] = {}
        for r in rejected:
            counts[r.get("reason", "?")] = counts.get(r.get("reason", "?"), 0) + 1
        why = ", ".join(f"{n} {reason}" for reason, n in sorted(counts.items(),
                                                                 key=lambda kv: -kv[1]))
        return (f"all {len(rejected)} candidate peak{'s' if len(rejected) > 1 else ''} "
                f"{'were' if len(rejected) > 1 else 'was'} rejected ({why}; listed below; "
                "docs/modes.md says how to keep them)")
    df = fps / n_frames
    lo = max(float(band[0]), int(meta.get("min_bin") or 3) * df)
    hi = float(band[1])
    if lo >= hi:
        return (f"nothing could be searched: {n_frames} frames at {fps:g} fps give bins of "
                f"{df:.4g} Hz, and the band {band[0]:g}-{hi:g} Hz has none above the lowest "
                f"searched ({lo:.4g} Hz); record longer or widen the band")
    floor = meta.get("noise_floor") or {}
    alarm = floor.get("false_alarm")
    text = (f"no peak in {lo:.4g}-{hi:g} Hz rose above the noise floor"
            + (f" (false alarm {alarm:g})" if alarm else "")
            + ("" if analysed == 0 else f"; {analysed} analysed"))
    if n_frames < MIN_FRAMES or short:
        text += (f"; a short record ({n_frames} frames, {n_frames / fps:.4g} s): weak lines "
                 "need a longer one")
    return text
