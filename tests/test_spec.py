"""System spec files (TOML): safe expression parsing, examples, and the bad-spec table."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
import sympy

import systems
from nlyap_opt.kernel.errors import ConfigError
from systems.spec import parse_expression, to_casadi

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _fun(s: systems.System) -> ca.Function:
    return ca.Function("f", [s.x, s.u], [s.f])


def _random(box, n, rng):
    box = np.asarray(box, dtype=float)
    return box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((n, box.shape[0]))


# ============================================================================ examples
def test_lorenz_spec_equals_hand_written_model(rng):
    s = systems.load_spec(EXAMPLES / "lorenz_controlled.toml")
    assert (s.kind, s.nx, s.nu, s.state_names, s.input_names) == (
        "model", 3, 1, ["x", "y", "z"], ["u"])
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 1)
    sigma, rho, beta = 10.0, 28.0, 8.0 / 3.0
    f = ca.vertcat(sigma * (x[1] - x[0]), x[0] * (rho - x[2]) - x[1] + u,
                   x[0] * x[1] - beta * x[2])
    hand = ca.Function("h", [x, u], [f])
    X, U = _random(s.state_box, 200, rng), _random(s.input_box, 200, rng)
    got, want = s.evaluate(X, U), np.array(hand(X.T, U.T)).T
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-13)
    np.testing.assert_allclose(s.A, [[-10, 10, 0], [28, -1, 0], [0, 0, -beta]], atol=1e-15)
    np.testing.assert_array_equal(s.B.ravel(), [0, 1, 0])
    assert s.declarations.B.ravel().tolist() == [0, 1, 0]
    d = systems.default_run_settings(s)
    assert (d["outer"], d["inner"], d["controller_scale"]) == (None, 0.1, 40.0)
    assert d["domain"] == {"type": "box", "box": s.state_box.tolist()}
    # a declared B: φ₀(x) is learned on an x-grid (control-affine model)
    assert d["dynamics"]["model"] == "control_affine"
    counts = d["dynamics"]["grid_counts"]
    assert len(counts) == 3 and all(c % 2 == 1 for c in counts)
    assert counts == [57] * 3 and np.prod(counts) <= 200_000 < np.prod([59] * 3)


def test_two_machine_spec_equals_hand_written_model(rng):
    s = systems.load_spec(EXAMPLES / "two_machine_power.toml")
    assert s.nu == 0 and s.known_state_derivatives == (0,)
    d = math.pi / 3
    X = _random(s.state_box, 300, rng)
    want = np.stack([X[:, 1], -0.5 * X[:, 1] - (np.sin(X[:, 0] + d) - np.sin(d))], axis=1)
    np.testing.assert_allclose(s.evaluate(X), want, rtol=1e-14, atol=1e-14)
    assert s.params["delta"] == pytest.approx(d, rel=1e-15)
    assert len(s.describe_assumptions()) == 2
    # the declared constants hold on the data (and a grid check passes)
    from nlyap_opt.learned.dynamics import Grid

    est = s.check_declarations(Grid(s.state_box, [31, 41]))
    assert est["slope"] <= 1.5 and est["second_difference"] <= 1.0


def test_factory_spec_and_csv_spec(tmp_path):
    s = systems.load_spec(EXAMPLES / "blackbox_pendulum.toml")
    assert s.kind == "callable"
    assert (s.run_overrides["outer"], s.run_overrides["inner"]) == (4.0, 0.4)
    assert s.run_overrides["dynamics"]["model"] == "control_affine"
    assert s.source.endswith("blackbox_pendulum.toml")
    # the csv spec, pointed at a freshly written small csv
    import importlib.util

    spec = importlib.util.spec_from_file_location("_w", EXAMPLES / "write_pendulum_csv.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.main(["--out", str(tmp_path / "data" / "pendulum.csv"), "--counts", "41", "41"])
    text = (EXAMPLES / "pendulum_csv.toml").read_text()
    (tmp_path / "p.toml").write_text(text)
    p = systems.load_spec(tmp_path / "p.toml")
    assert p.kind == "samples" and p.known_state_derivatives == (0,)
    from nlyap_opt.learned.dynamics import Grid

    assert p.samples.delta == Grid(s.state_box, [41, 41]).delta
    assert systems.default_run_settings(p)["dynamics"] == {"model": "control_affine",
                                                           "grid_counts": [41, 41]}


def test_expression_parser_functions_and_powers():
    a, b = sympy.symbols("a b", real=True)
    A, B = ca.SX.sym("a"), ca.SX.sym("b")
    cases = {
        "a^2 + b**3": lambda x, y: x**2 + y**3,
        "sqrt(a*a + 1) - abs(b) + sign(b)": lambda x, y: math.sqrt(x * x + 1) - abs(y)
        + math.copysign(1.0, y),
        "min(a, b, 0.5) + max(a, b)": lambda x, y: min(x, y, 0.5) + max(x, y),
        "atan2(b, a) + atan(a) + tanh(b) + exp(-a) + log(2 + b)": lambda x, y: math.atan2(y, x)
        + math.atan(x) + math.tanh(y) + math.exp(-x) + math.log(2 + y),
        "pow(a, 3) - 1/(1 - a/4) + pi + -b + +a": lambda x, y: x**3 - 1 / (1 - x / 4)
        + math.pi - y + x,
        "sin(a)*cos(b)/tan(1 + a^2) + 2.5e-1": lambda x, y: math.sin(x) * math.cos(y)
        / math.tan(1 + x * x) + 0.25,
    }
    for text, ref in cases.items():
        e = to_casadi(parse_expression(text, {"a": a, "b": b}), {a: A, b: B})
        f = ca.Function("f", [A, B], [e])
        for x, y in [(0.3, -0.7), (-1.2, 0.4), (0.9, 1.1)]:
            assert float(f(x, y)) == pytest.approx(ref(x, y), rel=1e-13, abs=1e-14), text


def test_parser_keeps_the_expression_as_written():
    # exp(log(a)) is not simplified to a: the verifier must still see log's domain (P10)
    a = sympy.Symbol("a", real=True)
    A = ca.SX.sym("a")
    e = to_casadi(parse_expression("exp(log(a))", {"a": a}), {a: A})
    ops = {ca.Function("f", [A], [e]).instruction_id(k)
           for k in range(ca.Function("f", [A], [e]).n_instructions())}
    assert ca.OP_LOG in ops


def test_parser_never_evaluates_code(tmp_path):
    marker = tmp_path / "pwned"
    text = f"__import__('os').system('touch {marker}')"
    with pytest.raises(ConfigError, match="only plain function calls are allowed"):
        parse_expression(text, {})
    with pytest.raises(ConfigError, match="function '__import__' is not allowed at column 1"):
        parse_expression("__import__('os')", {})
    for evil in ("().__class__", "[x for x in ()]", "open('f')", "globals()", "x1 if 1 else 2",
                 "{'a': 1}", "f'{1}'", "b'1'", "1j", "True"):
        with pytest.raises(ConfigError):
            parse_expression(evil, {"x1": sympy.Symbol("x1")})
    assert not marker.exists()


# ============================================================================ bad specs
GOOD = """
name = "t"
states = ["x1", "x2"]
inputs = ["u"]
state_box = [[-1, 1], [-1, 1]]
input_box = [[-2, 2]]
[parameters]
mu = 1.0
[rhs]
x1 = "x2"
x2 = "-x1 - mu*x2 + u"
"""

SAMPLES = """
name = "t"
states = ["x1", "x2"]
inputs = ["u"]
u_eq = [0.0]
[samples]
file = "s.csv"
"""


def _csv(rows=None, header="x1,x2,u,x1_dot,x2_dot", mutate=None):
    if rows is None:
        rows = []
        for a in (-1.0, 0.0, 1.0):
            for b in (-1.0, 0.0, 1.0):
                for u in (-1.0, 0.0, 1.0):
                    rows.append([a, b, u, b, -a - b + u])
    if mutate:
        rows = mutate([list(r) for r in rows])
    lines = ([header] if header else []) + [",".join(map(repr, r)) for r in rows]
    return "\n".join(lines) + "\n"


def _replace(old, new, base=GOOD):
    assert old in base
    return base.replace(old, new)


def _x1(expr):
    """GOOD with the right-hand side of x1 replaced by ``expr``."""
    return _replace('x1 = "x2"', f'x1 = "{expr}"')


BAD = [
    # (label, spec text, csv text or None, regex of the message)
    ("unknown top-level key", _replace('states =', 'stats = ["a"]\nstates ='), None,
     r"top level: unknown key 'stats'; did you mean 'states'\?"),
    ("unknown declared key", GOOD + "[declared]\nlipshitz = 3\n", None,
     r"declared: unknown key 'lipshitz'; did you mean 'lipschitz'\?"),
    ("unknown samples key", SAMPLES + "fil = 1\n", _csv(),
     r"samples: unknown key 'fil'; did you mean 'file'\?"),
    ("unknown symbol", _replace('"-x1 - mu*x2 + u"', '"-x1 - mu*y + u"'), None,
     r"rhs\.x2: unknown symbol 'y' at column 10 of '-x1 - mu\*y \+ u'"),
    ("did you mean", _replace('"-x1 - mu*x2 + u"', '"-x1 - mu*x22 + u"'), None,
     r"unknown symbol 'x22' .*did you mean 'x2'\?"),
    ("syntax error", _replace('"-x1 - mu*x2 + u"', '"-x1 - * x2"'), None,
     r"rhs\.x2: syntax error at column \d+ in '-x1 - \* x2'"),
    ("disallowed function", _x1('floor(x2)'), None,
     r"rhs\.x1: function 'floor' is not allowed .*\(allowed: sin, cos"),
    ("__import__", _x1("__import__('os').system('ls')"), None,
     r"rhs\.x1: .*'__import__'|rhs\.x1: only plain function calls"),
    ("attribute access", _x1('x2.real'), None,
     r"rhs\.x1: attribute access is not allowed"),
    ("lambda", _x1('(lambda: 1)()'), None, r"rhs\.x1: only plain function calls"),
    ("comparison", _x1('x2 < 1'), None, r"comparisons is not allowed"),
    ("string constant", _x1("'a'"), None, r"is not a real number"),
    ("division by zero", _x1('x2 + 1/0'), None, r"division by zero"),
    ("wrong arity", _x1('atan2(x2)'), None, r"atan2\(\) takes 2 arguments, got 1"),
    ("rhs for a non-state", GOOD + 'x3 = "x1"\n', None,
     r"rhs\.x3: 'x3' is not a state"),
    ("missing rhs", _replace('x2 = "-x1 - mu*x2 + u"\n', ''), None,
     r"rhs: no expression for \['x2'\]"),
    ("state box shape", _replace('state_box = [[-1, 1], [-1, 1]]', 'state_box = [[-1, 1]]'),
     None, r"state_box: has shape \(1, 2\); need 2 rows"),
    ("input box order", _replace('input_box = [[-2, 2]]', 'input_box = [[2, -2]]'), None,
     r"input_box: needs finite rows with lo < hi"),
    ("missing state box", _replace('state_box = [[-1, 1], [-1, 1]]\n', ''), None,
     r"state_box: missing; give 2 rows"),
    ("u_eq length", _replace('inputs = ["u"]', 'inputs = ["u"]\nu_eq = [0, 1]'), None,
     r"u_eq: must be 1 finite numbers"),
    ("not an equilibrium", _x1('x2 + 0.5'), None,
     r"the origin is not an equilibrium"),
    ("parameter clash", _replace('mu = 1.0', 'x1 = 1.0'), None,
     r"parameters\.x1: 'x1' cannot be a parameter name"),
    ("parameter expression", _replace('mu = 1.0', 'mu = "2*nu"'), None,
     r"parameters\.mu: unknown symbol 'nu'"),
    ("bad name", _replace('states = ["x1", "x2"]', 'states = ["x1", "sin"]'), None,
     r"states: 'sin' is not a usable name"),
    ("known not a state", _replace('inputs = ["u"]', 'inputs = ["u"]\nknown = ["x9"]'), None,
     r"known: 'x9' is not a state"),
    ("two sources", _replace('inputs = ["u"]', 'inputs = ["u"]\nu_eq = [0.0]')
     + '[samples]\nfile = "s.csv"\n', _csv(),
     r"rhs\.x1: the dynamics come from the sample file"),
    ("factory with states", 'factory = "m.py:make"\nstates = ["a"]\n', None,
     r"factory: the factory defines the system; remove \['states'\]"),
    ("factory missing file", 'factory = "nofile.py:make"\n', None,
     r"factory: file .*nofile.py' not found"),
    ("invalid toml", "name = \n", None, r"not valid TOML"),
    ("run not a table", GOOD.replace('name = "t"', 'name = "t"\nrun = 3'), None,
     r"run: must be a table"),
    ("missing u_eq (samples)", SAMPLES.replace("u_eq = [0.0]\n", ""), _csv(),
     r"u_eq: missing; a system given by samples needs the declared equilibrium input"),
    ("ragged csv", SAMPLES, _csv(mutate=lambda r: r[:3] + [r[3][:4]] + r[4:]),
     r"s\.csv: line 5 has 4 fields, the first line has 5; .*ragged"),
    ("irregular grid", SAMPLES,
     _csv(mutate=lambda r: [[a * (0.5 if a < 0 else 1)] + x for a, *x in r]),
     r"axis 'x1' is not equally spaced"),
    ("duplicate node", SAMPLES, _csv(mutate=lambda r: r + [r[4]]),
     r"grid node \(x1=-1, x2=0, u=0\) appears twice \(rows 5 and 28\)"),
    ("missing node", SAMPLES, _csv(mutate=lambda r: r[:-1]),
     r"the grid is incomplete: node \(x1=1, x2=1, u=1\) is missing"),
    ("NaN value", SAMPLES, _csv(mutate=lambda r: r[:2] + [r[2][:4] + [math.nan]] + r[3:]),
     r"value 'x2_dot' of sample row 3 is nan"),
    ("unknown column", SAMPLES, _csv(header="x1,x2,u,x1_dot,x2dot"),
     r"unknown column 'x2dot'; did you mean 'x2_dot'\?"),
    ("csv without header", SAMPLES, _csv(header=None), r"the csv has no header"),
    ("K_f too small", SAMPLES + "[declared]\nlipschitz = 0.5\n", _csv(),
     r"declared K_f = 0\.5 is below the finite-difference slope 1\.41421 .*declare K_f ≥ 1\.41421"),
    ("B contradicted", SAMPLES + "[declared]\ninput_matrix = [[0.0], [2.0]]\n", _csv(),
     r"declared input matrix B is contradicted"),
    ("B wrong shape", GOOD + "[declared]\ninput_matrix = [[0.0, 1.0]]\n", None,
     r"declared: declared input_matrix has shape \(1, 2\)|declared: input_matrix has shape"),
    ("K_f too small (model)", GOOD + "[declared]\nlipschitz = 1.0\n", None,
     r"sys.toml: declared K_f = 1 is below the finite-difference slope 1\.[4-9]"),
    ("H too small (model)", _x1("x2 + 3*x1^2") + "[declared]\nhessian = 1.0\n", None,
     r"sys.toml: declared H = 1 is below the second-difference estimate 6 of "
     r"\|∂²f_0/∂x1∂x1\|"),
    ("input box without inputs", _replace('inputs = ["u"]\n', '').replace(" + u", ""), None,
     r"input_box: the system has no inputs; remove it"),
    ("u_eq without inputs", _replace('inputs = ["u"]\n', 'u_eq = [0.0]\n').replace(
        "input_box = [[-2, 2]]\n", "").replace(" + u", ""), None,
     r"u_eq: the system has no inputs; remove it"),
    ("K_f per component length", GOOD + "[declared]\nlipschitz = [1, 2, 3]\n", None,
     r"declared lipschitz has 3 entries"),
    ("depends_on contradicted", SAMPLES + '[declared]\ndepends_on = { x2 = ["x1", "u"] }\n',
     _csv(), r"declared depends_on is contradicted by the samples: x2' changes by 1 "
             r"between z = .* along 'x2'"),
    ("depends_on unknown variable", GOOD + '[declared]\ndepends_on = { x2 = ["x1", "y"] }\n',
     None, r"declared depends_on names variable 'y'; the system has x1, x2, u"),
    ("depends_on unknown state", SAMPLES + '[declared]\ndepends_on = { x3 = ["x1"] }\n',
     _csv(), r"declared depends_on names state 'x3'; the system has x1, x2"),
    ("depends_on not a table", GOOD + '[declared]\ndepends_on = ["x2"]\n', None,
     r"declared depends_on must be a table \{state: \[variables\]\}"),
    ("known without expression", SAMPLES.replace('u_eq', 'known = ["x1"]\nu_eq'), _csv(),
     r"known components \['x1'\] need an expression in \[rhs\]"),
    ("sample file missing", SAMPLES.replace("s.csv", "none.csv"), None,
     r"sample file .*none.csv' not found"),
]


@pytest.mark.parametrize("label, text, csv_text, msg", BAD, ids=[b[0] for b in BAD])
def test_bad_spec(label, text, csv_text, msg, tmp_path):
    path = tmp_path / "sys.toml"
    path.write_text(textwrap.dedent(text))
    if csv_text is not None:
        (tmp_path / "s.csv").write_text(csv_text)
    (tmp_path / "m.py").write_text("raise RuntimeError('must not be imported')\n")
    with pytest.raises(ConfigError) as err:
        systems.load_spec(path)
    text = str(err.value)
    assert "\n" not in text, text
    assert str(path) in text or "s.csv" in text or "none.csv" in text, text
    assert __import__("re").search(msg, text), text


def test_good_specs_load(tmp_path):
    assert len(BAD) >= 15
    path = tmp_path / "sys.toml"
    path.write_text(GOOD)
    s = systems.load_spec(path)
    assert s.has_model and s.u_eq.tolist() == [0.0]
    (tmp_path / "s.csv").write_text(_csv())
    path.write_text(SAMPLES + "[declared]\nlipschitz = 1.8\ninput_matrix = [[0.0], [1.0]]\n")
    s = systems.load_spec(path)
    assert s.kind == "samples" and s.samples.delta == pytest.approx(math.sqrt(3) / 2)
    # a csv without header, columns declared (in another order)
    rows = _csv(header=None).splitlines()
    perm = [[r.split(",")[i] for i in (3, 0, 4, 1, 2)] for r in rows]
    (tmp_path / "s.csv").write_text("\n".join(",".join(r) for r in perm) + "\n")
    text = SAMPLES.replace('file = "s.csv"',
                           'file = "s.csv"\ncolumns = ["x1_dot", "x1", "x2_dot", "x2", "u"]')
    path.write_text(text)
    t = systems.load_spec(path)
    np.testing.assert_array_equal(t.samples.values, s.samples.values)


def test_docstring_example_spec_loads(tmp_path):
    import systems.spec as sp

    doc = sp.__doc__
    text = doc[doc.index('    name = "pendulum"'):doc.index("With ``[samples]``")]
    (tmp_path / "p.toml").write_text(textwrap.dedent(text))
    s = systems.load_spec(tmp_path / "p.toml")
    assert s.has_model and s.run_overrides == {"outer": 4.0}
    said = s.describe_assumptions()   # K_f, H, B, sample error, dependency structure
    assert len(said) == 5 and said[-1].startswith(
        "Dependency structure (declared): omega' depends on (theta, omega, torque) only")
    np.testing.assert_allclose(s.B.ravel(), s.declarations.B.ravel(), rtol=1e-15)


def test_a_dependency_the_samples_agree_with_is_kept_and_listed(tmp_path):
    """``x1' = x2`` reads only x2: declared so, it passes the check on the samples and is
    listed with the assumptions; ``inputs: model`` gives φ's block that column alone."""
    from nlyap_opt.learned.dynamics import input_columns

    path = tmp_path / "sys.toml"
    path.write_text(SAMPLES + '[declared]\ndepends_on = { x1 = ["x2"], x2 = [0, "x2", "u"] }\n')
    (tmp_path / "s.csv").write_text(_csv())
    s = systems.load_spec(path)
    assert s.declarations.dependencies(s.state_names, s.input_names) == {0: (1,), 1: (0, 1, 2)}
    said = [a for a in s.describe_assumptions() if a.startswith("Dependency structure")]
    assert said and "x1' depends on (x2) only; x2' depends on (x1, x2, u) only" in said[0]
    assert input_columns(s, "full", [0, 1], "model") == [[1], [0, 1, 2]]
    assert input_columns(s, "full", [0, 1], "all") == [[0, 1, 2], [0, 1, 2]]


def test_a_factory_systems_name_must_be_plain_when_the_file_gives_none(tmp_path):
    """The name of a factory's system names runs/NAME as a spec's own name does: one
    leaving runs/ is refused with the fix; the file's own name replaces it."""
    (tmp_path / "m.py").write_text(
        "import casadi as ca\nimport systems\n"
        "def make():\n"
        "    x = ca.SX.sym('x', 1)\n"
        "    return systems.System('../../escape', x, None, -x, state_box=[[-1, 1]])\n")
    (tmp_path / "f.toml").write_text('factory = "m.py:make"\n')
    with pytest.raises(ConfigError, match=r"name: must be a plain name.*'\.\./\.\./escape'"):
        systems.load_spec(tmp_path / "f.toml")
    (tmp_path / "g.toml").write_text('name = "fine"\nfactory = "m.py:make"\n')
    assert systems.load_spec(tmp_path / "g.toml").name == "fine"
