"""Property-based tests of load_graph on mutated files: a damaged file must give EITHER a one-line
GraphFileError naming a line of the file, OR exactly the graph that its intact lines describe."""

import re

import gtsam
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import dataset
from gtsam_schwarz.io import GraphFileError, load_graph

G2O_LINES = [
    "VERTEX_SE2 0 0 0 0",
    "VERTEX_SE2 1 1.0 0.1 0.2",
    "VERTEX_SE2 2 2.0 0.3 0.4",
    "VERTEX_SE2 3 2.1 1.2 1.6",
    "VERTEX_SE2 4 1.1 1.1 3.0",
    "VERTEX_SE2 5 0.1 1.0 -2.9",
    "EDGE_SE2 0 1 1 0 0.2 50 1 2 60 3 70",
    "EDGE_SE2 1 2 1 0.1 0.2 50 0 0 50 0 100",
    "EDGE_SE2 2 3 1 0 1.2 40 0 0 40 0 90",
    "EDGE_SE2 3 4 1 0 1.4 50 0 0 50 0 100",
    "EDGE_SE2 4 5 1 0 0.1 50 0 0 50 0 100",
    "EDGE_SE2 5 0 1 0 1.5 50 0 0 50 0 100",
    "EDGE_SE2 0 3 2.3 1.2 1.6 10 0 0 10 0 20",
    "EDGE_SE2 1 4 1.4 0.9 2.8 10 -1 0.5 12 0.2 20",
]


def _to_toro(line: str) -> str:
    """The same record in TORO: information (I11 I12 I13 I22 I23 I33) -> (Ixx Ixy Iyy Itt Ixt Iyt)."""
    tag, *rest = line.split()
    if tag == "VERTEX_SE2":
        return " ".join(["VERTEX2"] + rest)
    i11, i12, i13, i22, i23, i33 = rest[5:]
    return " ".join(["EDGE2"] + rest[:5] + [i11, i12, i22, i33, i13, i23])


TORO_LINES = [_to_toro(line) for line in G2O_LINES]
# tokens that are never a valid field: not numbers, not finite, not ids, or a comment start
JUNK = ["abc", "nan", "inf", "-inf", "1e999", "1.2.3", "#", "0x1F", "--1", "1_0", "+-", "\x00", "é", "EDGE", "3.5", "3.5x"]
SETTINGS = settings(max_examples=100, deadline=None, database=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def mutate(data, lines: list[str]) -> list[tuple[str, bool]]:
    """1-3 random edits; each resulting line is (text, intact) where intact means 'an original line'."""
    cur = [(line, True) for line in lines]
    for _ in range(data.draw(st.integers(1, 3), label="edits")):
        kind = data.draw(st.sampled_from(["delete line", "duplicate line", "swap lines",
                                          "delete token", "duplicate token", "replace token"]), label="kind")
        k = data.draw(st.integers(0, len(cur) - 1), label="line")
        text, intact = cur[k]
        if kind == "delete line":
            del cur[k]
        elif kind == "duplicate line":
            cur.insert(data.draw(st.integers(0, len(cur)), label="at"), (text, intact))
        elif kind == "swap lines":
            j = data.draw(st.integers(0, len(cur) - 1), label="with")
            cur[k], cur[j] = cur[j], cur[k]
        else:
            tokens = text.split()
            if not tokens:
                continue
            t = data.draw(st.integers(0, len(tokens) - 1), label="token")
            if kind == "delete token":
                del tokens[t]
            elif kind == "duplicate token":
                tokens.insert(t, tokens[t])
            else:
                junk = data.draw(st.sampled_from(JUNK), label="junk")
                if junk == "3.5" and t >= (2 if tokens[0].startswith("VERTEX") else 3):
                    junk = "3.5x"  # a different valid number would be a valid (undetectable) line
                tokens[t] = junk
            cur[k] = (" ".join(tokens), False)
    return cur


def try_load(path):
    try:
        return load_graph(path)
    except GraphFileError as exc:
        return exc


def same_graph(a, b):
    """Same factors (keys in order, errors at the values and perturbed values) and same values."""
    assert (a.dimension, a.poses, a.edges, a.format, a.prior_added) == (b.dimension, b.poses, b.edges, b.format,
                                                                       b.prior_added)
    assert [tuple(a.graph.at(k).keys()) for k in range(a.graph.size())] == \
           [tuple(b.graph.at(k).keys()) for k in range(b.graph.size())]
    assert a.initial.equals(b.initial, 1e-12)
    for seed in (None, 1, 2):
        v = gtsam.Values(a.initial)
        if seed is not None:
            (gtsam.utilities.perturbPose2 if a.dimension == 2 else gtsam.utilities.perturbPose3)(v, 0.2, 0.1, seed)
        ea, eb = a.graph.error(v), b.graph.error(v)
        assert abs(ea - eb) <= 1e-12 * max(1.0, abs(eb))


def check_mutation(tmp_path, data, lines, suffix):
    """The property: mutated file -> clean error naming a line, or the intact lines' graph."""
    mutated = mutate(data, lines)
    path = tmp_path / f"mutated{suffix}"
    path.write_text("\n".join(text for text, _ in mutated) + "\n", encoding="utf-8")
    intact_path = tmp_path / f"intact{suffix}"
    intact_path.write_text("\n".join(text for text, ok in mutated if ok) + "\n", encoding="utf-8")
    result, reference = try_load(path), try_load(intact_path)
    if isinstance(result, GraphFileError):
        message = str(result)
        assert "\n" not in message
        match = re.fullmatch(re.escape(str(path)) + r"(?::(\d+))?: .+", message)
        assert match, message
        if match.group(1) is None:  # whole-file errors ("no edges") happen only if the intact lines fail too
            assert isinstance(reference, GraphFileError), message
        else:
            line = int(match.group(1))
            assert 1 <= line <= len(mutated), message
            # the line at fault was damaged, or the intact lines alone are bad too (e.g. a deleted vertex)
            assert not mutated[line - 1][1] or isinstance(reference, GraphFileError), message
    else:
        assert not isinstance(reference, GraphFileError), reference
        same_graph(result, reference)


@SETTINGS
@given(data=st.data())
def test_mutated_g2o_file(tmp_path, data):
    check_mutation(tmp_path, data, G2O_LINES, ".g2o")


@SETTINGS
@given(data=st.data())
def test_mutated_toro_file(tmp_path, data):
    check_mutation(tmp_path, data, TORO_LINES, ".graph")


@pytest.fixture(scope="module")
def tiny3d_lines():
    return [line for line in dataset("tinyGrid3D.g2o").read_text().splitlines() if line.strip()]


@pytest.mark.datasets
@SETTINGS
@given(data=st.data())
def test_mutated_3d_file(tmp_path, data, tiny3d_lines):
    check_mutation(tmp_path, data, tiny3d_lines, ".g2o")


def test_unmutated_bases_load(tmp_path):
    """The bases themselves are valid (and agree with GTSAM's readers), so every failure is a mutation's."""
    graphs = []
    for name, lines in [("a.g2o", G2O_LINES), ("a.graph", TORO_LINES)]:
        p = tmp_path / name
        p.write_text("\n".join(lines) + "\n")
        g = load_graph(p)
        assert (g.poses, g.edges) == (6, 8)
        ref = gtsam.readG2o(str(p)) if name.endswith(".g2o") else gtsam.load2D(
            str(p), noiseFormat=gtsam.NoiseFormat.NoiseFormatTORO)
        assert np.isclose(g.graph.error(g.initial), ref[0].error(g.initial), rtol=1e-12)
        graphs.append(g)
    assert graphs[0].format == "g2o" and graphs[1].format == "toro"
    assert np.isclose(graphs[0].graph.error(graphs[0].initial), graphs[1].graph.error(graphs[0].initial), rtol=1e-12)
