"""Fuzzing suite files: the shipped ``smoke`` suite's TOML dict with values replaced by NaN,
inf, negative, zero, huge numbers and wrong types, and unknown keys added, table-driven over
every key and with hypothesis. Parsing (and expanding into the task graph) must accept the
file or raise :class:`SuiteError` with one line naming the file and the key; a non-finite
number, a wrong type or an unknown key is never accepted."""

from __future__ import annotations

import copy
import math
import tomllib

import pytest

from vvtbench.bench import SUITES_DIR, SuiteError, build_graph, parse_suite


@pytest.fixture(autouse=True, scope="module")
def _descriptions_kept_across_cases():
    """Each case expands a graph, which describes every solver in a sealed child. A description
    is keyed by the plug-in, its config and the mtimes of the files it names, so keeping them
    across cases changes no outcome; it spares hundreds of identical children."""
    import vvtbench.solving.sealed as sealed

    forget = sealed.forget_descriptions
    sealed.forget_descriptions = lambda: None
    yield
    sealed.forget_descriptions = forget
    forget()


SMOKE = tomllib.loads((SUITES_DIR / "smoke.toml").read_text())
SOURCE = "fuzz.toml"

NUMBERS = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf, "negative": -1, "zero": 0,
           "huge": 1e300, "hugeint": 10**30, "negfloat": -2.5}
TYPES = {"string": "x", "bool": True, "list": [], "table": {}, "list_of_str": ["a"]}
MUST_REJECT = {"nan", "inf", "-inf", "unknown_key"}
# keys whose values are free text or names (a wrong *kind* of text is not an error there)
TEXT_KEYS = {"name", "description"}


def _leaves(d, path=()):
    if isinstance(d, dict):
        yield path, d
        for k, v in d.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            yield from _leaves(v, (*path, i))
    else:
        yield path, d


def _set(data, path, value):
    node = data
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = value


def cases():
    """(case id, kind, mutated dict) for every key of the smoke suite."""
    out = []
    for path, value in _leaves(SMOKE):
        name = ".".join(map(str, path)) or "<top>"
        if isinstance(value, dict):
            d = copy.deepcopy(SMOKE)
            node = d
            for p in path:
                node = node[p]
            node["bogus_key"] = 1
            out.append((f"{name}+bogus_key", "unknown_key", d))
            continue
        for kind, new in {**NUMBERS, **TYPES}.items():
            if type(new) is type(value) and new == value:
                continue
            d = copy.deepcopy(SMOKE)
            _set(d, path, new)
            out.append((f"{name}={kind}", kind, d))
    return out


def outcome(data) -> tuple[str, str]:
    """('accepted' | 'clear' | 'unclear' | 'crashed', message)."""
    try:
        suite = parse_suite(data, SOURCE)
        _, runs = build_graph(suite, suite.solvers)
    except SuiteError as error:
        msg = str(error)
        clear = "\n" not in msg and msg.startswith(f"{SOURCE}: ") and "key '" in msg
        return ("clear" if clear else "unclear"), msg
    except Exception as error:  # noqa: BLE001 -- what the fuzz looks for
        return "crashed", f"{type(error).__name__}: {error}"
    errors = sorted({r.setup_error for r in runs if r.setup_error})
    if errors:  # a solver that does not load or configure: its rows are errors
        clear = all("\n" not in e for e in errors)
        return ("clear" if clear else "unclear"), errors[0]
    return "accepted", ""


CASES = cases()


def test_the_table_covers_every_key():
    assert len(CASES) > 150
    assert outcome(copy.deepcopy(SMOKE))[0] == "accepted"


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_mutated_smoke_suite(case):
    cid, kind, data = case
    result, msg = outcome(data)
    assert result in ("accepted", "clear"), (cid, result, msg)
    if kind in MUST_REJECT:
        assert result == "clear", (cid, "accepted silently")
    leaf = cid.split("=")[0].split(".")[-1]
    if kind in TYPES and leaf not in TEXT_KEYS and result == "accepted":
        # a wrong type is accepted only where the suite does not care about the type
        # (scene overrides are checked when the scene is resolved, in build_graph)
        raise AssertionError((cid, "wrong type accepted"))


hypothesis = pytest.importorskip("hypothesis")
st = hypothesis.strategies

VALUES = st.one_of(st.sampled_from(list(NUMBERS.values()) + list(TYPES.values())),
                   st.floats(allow_nan=True, allow_infinity=True),
                   st.integers(min_value=-(10**20), max_value=10**20),
                   st.text(max_size=5))
PATHS = [p for p, v in _leaves(SMOKE) if p and not isinstance(v, dict)]


# derandomized: a stop's CI run must not fail on a case no one has seen (as test_fuzz_scene)
@hypothesis.settings(max_examples=60, deadline=None, derandomize=True,
                     suppress_health_check=[hypothesis.HealthCheck.too_slow])
@hypothesis.given(st.lists(st.tuples(st.sampled_from(PATHS), VALUES), min_size=1, max_size=3))
@hypothesis.example([(("scenes", 0), "\n")])  # a raw newline in a name made the error 2 lines
def test_random_mutations(mutations):
    data = copy.deepcopy(SMOKE)
    for path, value in mutations:
        try:
            _set(data, path, value)
        except (TypeError, IndexError, KeyError):  # an earlier mutation changed the parent
            continue
    result, msg = outcome(data)
    assert result in ("accepted", "clear"), (mutations, result, msg)
    if any(isinstance(v, float) and not math.isfinite(v) for _, v in mutations):
        assert result == "clear" or all(  # unless another mutation replaced that value
            not (isinstance(v, float) and not math.isfinite(v))
            for _, v in _leaves(data) if not isinstance(v, dict))
