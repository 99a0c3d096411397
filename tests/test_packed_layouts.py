"""One declaration per packed layout (issue 62, item 2): blf_gym.jit.layout against what the code
packs and computes, and a search for literal offsets into packed arrays anywhere else in blf_gym.

The declarations are checked against independent computations: the parameter dataclasses' own
field values (what ``pack`` must put at each declared offset), the NumPy dynamics and reference
(what the compiled fillers must put there), and the status and record columns against an episode's
known events."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from blf_gym.jit import layout as L
from blf_gym.model.params import ArmParams, joint_scenario, preset

ROOT = Path(__file__).resolve().parents[1]

# -- the search ------------------------------------------------------------------------------------

_N = {"n", "nn"}


def _mentions_n(e: ast.AST) -> bool:
    return any(isinstance(x, ast.Name) and x.id in _N for x in ast.walk(e))


def _is_n(e: ast.AST | None) -> bool:
    return isinstance(e, ast.Name) and e.id in _N


def _offset(e: ast.AST | None) -> bool:
    """An expression that places something at a position counted in joints: ``k * n`` with a
    literal k >= 2, or ``n`` added to or subtracted from anything (``n + i``, ``2 * n + 1``).
    A row-major index ``i * n + j`` is neither."""
    if e is None:
        return False
    for x in ast.walk(e):
        if isinstance(x, ast.BinOp) and isinstance(x.op, ast.Mult):
            for lit, other in ((x.left, x.right), (x.right, x.left)):
                if isinstance(lit, ast.Constant) and type(lit.value) is int and lit.value >= 2 and _mentions_n(other):
                    return True
        if isinstance(x, ast.BinOp) and isinstance(x.op, (ast.Add, ast.Sub)) and (_is_n(x.left) or _is_n(x.right)):
            return True
    return False


def _literal_slice(s: ast.Slice) -> bool:
    if _is_n(s.lower) or _offset(s.lower):
        return True
    up = s.upper
    # start : start + n is a part of n entries at a declared start, not an offset of its own
    if (isinstance(up, ast.BinOp) and isinstance(up.op, ast.Add) and s.lower is not None
            and ast.dump(up.left) == ast.dump(s.lower) and _is_n(up.right)):
        return False
    return _offset(up)


def literal_offsets(source: str) -> list[int]:
    """Lines of ``source`` that subscript an array at a literal position counted in joints."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Subscript):
            continue
        items = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
        for it in items:
            if (_literal_slice(it) if isinstance(it, ast.Slice) else (_is_n(it) or _offset(it))):
                lines.append(node.lineno)
                break
    return sorted(set(lines))


def test_the_search_finds_literal_offsets_and_passes_declared_ones():
    """The search itself, on what it must find and what it must let through."""
    found = ("x[n : 2 * n]", "w[4 * n : 6 * n]", "ref[n + i]", "a[2 * n]", "plant[2 * n + 1 + k]", "v[n:]",
             "nom[nn + 3 * n + i]", "s[b, 2 * n + j]")
    passed = ("M[i * n + j]", "x[:n]", "x[off : off + n]", "p[at(_P, n)]", "r[k]", "L[j * n + k + 1]",
              "fixed(x, at(_S_QD, n), n)[i]")
    for expr in found:
        assert literal_offsets(expr) == [1], expr
    for expr in passed:
        assert literal_offsets(expr) == [], expr


def test_no_literal_offset_into_a_packed_array_outside_the_layout_module():
    bad = {}
    for f in sorted((ROOT / "blf_gym").rglob("*.py")):
        if f.name == "layout.py" and f.parent.name == "jit":
            continue
        lines = literal_offsets(f.read_text())
        if lines:
            bad[str(f.relative_to(ROOT))] = lines
    assert not bad, f"offsets written by hand (derive them from blf_gym.jit.layout): {bad}"


# -- the declarations against independent computations ----------------------------------------------


@pytest.mark.parametrize("n", [2, 3, 5])
def test_every_declared_offset_of_the_packed_scenario_holds_its_fields_value(n):
    """Scenario.pack_plant / pack_reference and BoundParams.pack against the dataclasses' fields,
    read by the declared names (a reordered declaration or packer breaks this)."""
    sc = preset("paper-0.1hz") if n == 3 else joint_scenario(n)
    plant = sc.pack_plant()
    assert plant.shape == (L.PLANT.length(n),)
    np.testing.assert_array_equal(plant[L.PLANT.slice("lengths", n)], sc.arm.lengths)
    np.testing.assert_array_equal(plant[L.PLANT.slice("masses", n)], sc.arm.masses)
    assert plant[L.PLANT.slice("gravity", n)][0] == sc.arm.gravity
    fields = {**dataclasses.asdict(sc.friction), **dataclasses.asdict(sc.dead_zone), **dataclasses.asdict(sc.sim)}
    for name in L.PLANT_TAIL:
        got = plant[L.PLANT.slice(name, n)][0]
        if name in ("f_x", "f_y", "moment"):
            assert got == sc.force.wrench[("f_x", "f_y", "moment").index(name)]
        elif name == "onset":
            assert got == sc.force.onset
        else:
            assert got == float(fields[name]), name
    bp = sc.bounds.pack()
    for name in L.BOUNDS_PACK:
        assert bp[L.BOUNDS.index(name)] == getattr(sc.bounds, name)
    rp = sc.pack_reference()
    assert rp.shape == (L.REFERENCE.length(n),)
    assert rp[L.REFERENCE.index("frequency")] == sc.reference.frequency
    assert L.REFERENCE_KINDS[int(rp[L.REFERENCE.index("kind")])] == sc.reference.kind
    if sc.reference.kind == "joint":
        np.testing.assert_array_equal(rp[L.REFERENCE.slice("amplitude", n)], sc.reference.amplitudes)
        np.testing.assert_array_equal(rp[L.REFERENCE.slice("offset", n)], sc.reference.offsets)
        np.testing.assert_allclose(rp[L.REFERENCE.slice("sin_phase", n)], np.sin(sc.reference.phases))


@pytest.mark.parametrize("n", [2, 3, 4])
def test_the_nominal_signal_holds_the_numpy_models_terms_where_declared(n):
    """nominal_model_into (compiled) against blf_gym.model.dynamics' NumPy functions, read by the
    declared parts, and the operators that read it back."""
    from blf_gym.model.dynamics import gravity, mass_matrix
    from blf_gym.plugins.blocks import mass_solve, nominal_model_into

    rng = np.random.default_rng(n)
    arm = ArmParams(lengths=tuple(rng.uniform(0.3, 1.0, n)), masses=tuple(rng.uniform(0.5, 2.0, n)))
    y = rng.uniform(-1.5, 1.5, n)
    nom = np.full(L.NOMINAL.length(n), np.nan)
    nominal_model_into(y, arm.pack(), nom, np.zeros(L.PLUGIN_WORK.length(n)))
    M = mass_matrix(y, arm)
    np.testing.assert_allclose(nom[L.NOMINAL.slice("M", n)].reshape(n, n), M, rtol=1e-13)
    np.testing.assert_allclose(nom[L.NOMINAL.slice("G", n)], gravity(y, arm), rtol=1e-13, atol=1e-13)
    th = np.cumsum(y)
    trig = nom[L.NOMINAL.slice("trig", n)]
    np.testing.assert_allclose(trig[L.TRIG.slice("cos", n)], np.cos(th), atol=1e-15)
    np.testing.assert_allclose(trig[L.TRIG.slice("sin", n)], np.sin(th), atol=1e-15)
    b = rng.normal(size=n)
    nom[L.NOMINAL.slice("arm", n)] = arm.pack()
    out = np.empty(n)
    mass_solve(nom, b, out)
    np.testing.assert_allclose(out, np.linalg.solve(M, b), rtol=1e-10)


def test_the_bound_and_reference_signals_are_where_declared():
    from blf_gym.model.bounds import bounds_into, error_bounds
    from blf_gym.model.reference import joint_reference, reference_into

    sc = preset("paper-0.1hz")
    for t in (0.0, 0.37, 2.5):
        bnd = np.empty(L.BOUND.length())
        bounds_into(t, sc.bounds.pack(), bnd)
        ka, kb = error_bounds(t, sc.bounds)
        assert bnd[L.BOUND.index("k_a")] == pytest.approx(ka, rel=1e-14)
        assert bnd[L.BOUND.index("k_b")] == pytest.approx(kb, rel=1e-14)
        for n, s in ((3, sc), (4, joint_scenario(4))):
            ref = np.empty(L.REF.length(n))
            reference_into(t, s.pack_reference(), s.arm.pack(), ref)
            for name, value in zip(L.REFERENCE_SIGNALS, joint_reference(t, s)):
                np.testing.assert_allclose(ref[L.REF.slice(name, n)], value, rtol=1e-12, atol=1e-12)


def test_the_recorded_channels_and_status_columns_are_where_declared():
    """An episode's record read by the declared channels against the trajectory's own relations
    (e1 = q - q_ref, the saturation flag where |u| reaches the limit), and its status by name."""
    from blf_gym.kernel.simulate import simulate

    sc = dataclasses.replace(preset("paper-0.1hz"), sim=dataclasses.replace(preset("paper-0.1hz").sim, duration=0.2))
    tr = simulate(sc, "proposed", "leso")
    np.testing.assert_array_equal(tr.e1, tr.q - tr.q_ref)
    np.testing.assert_allclose(tr.t, np.arange(tr.n_samples) * sc.sim.sample_period, rtol=1e-12, atol=1e-15)
    assert np.all((tr.saturated > 0) == (np.abs(tr.u) >= sc.sim.max_torque))
    assert L.STATUS_COLUMNS.index("first_violating_step") == L.STATUS.index("first_violating_step")
    assert tr.step_violations == 0 and tr.first_violation_step_time is None


def test_a_pack_rejects_a_part_declared_twice_and_reports_offsets_by_name():
    with pytest.raises(ValueError, match="declared twice"):
        L.Pack("x", [("a", 1), ("a", L.N)])
    p = L.Pack("x", [("a", 2), ("b", L.N), ("c", L.NN)])
    assert p.offsets(3) == {"a": (0, 2), "b": (2, 3), "c": (5, 9)} and p.length(3) == 14
    with pytest.raises(ValueError, match="depends on n"):
        p.index("c")
