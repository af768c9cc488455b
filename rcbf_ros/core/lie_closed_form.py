"""Barrier terms and RCBF-QP rows of ONE state in closed form, as generated Python on floats.

The same math as ``rcbf_ros.core.rcbf.barrier_terms`` and ``rcbf_ros.core.qp.build_rcbf_qp``,
evaluated without autograd for the per-step filter (B = 1, where torch's per-operation overhead
is most of the cost); the batched torch path stays the definition the learner differentiates
through, and the tests hold the two equal. Each problem's Lie derivatives, cascades and rows
become straight-line float code generated once at construction; a problem without a closed
form (a system or family given by dotted path) keeps the autograd path.

Design notes (the derivation, the code generator): docs/DESIGN.md#closed-form-lie-derivatives
"""
from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import numpy as np

from rcbf_ros.core.barriers import (
    BandBarrier,
    BarrierFamily,
    Cascaded,
    CircleObstacles,
    HalfPlane,
    PairGap,
    QuadraticRows,
)
from rcbf_ros.core.dynamics import (
    CLOSED_FORM_SYSTEMS,
    DriftSource,
    Entry,
    SOURCE_NAMESPACE,
    state_names,
)
from rcbf_ros.core.rcbf import RCBFProblem

MAX_CASCADE_DEPTH = 2
"""Deepest cascade with a closed form here (the built-in configs use up to 2)."""
_QUADRATIC_FAMILIES = (BandBarrier, CircleObstacles, HalfPlane, PairGap)


class NumpyTerms(NamedTuple):
    """:class:`~rcbf_ros.core.rcbf.BarrierTerms` of one state (K barriers), numpy float64."""

    h: np.ndarray
    """(K,) h_i(x)."""
    grad_h: np.ndarray
    """(K, n_x) grad h_i(x)."""
    lf_h: np.ndarray
    """(K,) L_f h_i(x)."""
    lg_h: np.ndarray
    """(K, n_u) L_g h_i(x)."""


def unwrap_cascades(family: BarrierFamily) -> tuple[BarrierFamily, list[Cascaded]]:
    """The base family under a stack of cascades, and the cascade levels (innermost first)."""
    levels = []
    while type(family) is Cascaded:
        levels.append(family)
        family = family.base
    return family, levels[::-1]


def _cascade_weights(gammas: Sequence[float]) -> tuple[float, float, float]:
    """beta of the module docstring: h_top = sum_l beta_l L_f^l h for a cascade's gains."""
    if len(gammas) == 0:
        return 1.0, 0.0, 0.0
    if len(gammas) == 1:
        return float(gammas[0]), 1.0, 0.0
    g1, g2 = (float(g) for g in gammas)
    return g1 * g2, g1 + g2, 1.0


# --- polynomials in named floats -------------------------------------------------------------

Poly = dict[tuple[str, ...], float]
"""sum of coefficient * product of named floats: {sorted names: coefficient}; () holds the
constant. No entry has a zero coefficient (a zero is the empty dict)."""


def _constant(value: float) -> Poly:
    return {(): float(value)} if value != 0.0 else {}


def _atom(name: str) -> Poly:
    return {(name,): 1.0}


def _entry(entry: Entry) -> Poly:
    """A :class:`DriftSource` entry (a constant or a name) as a polynomial."""
    return _atom(entry) if isinstance(entry, str) else _constant(entry)


def _plus(*polys: Poly) -> Poly:
    total: Poly = {}
    for poly in polys:
        for monomial, coefficient in poly.items():
            total[monomial] = total.get(monomial, 0.0) + coefficient
    return {monomial: c for monomial, c in total.items() if c != 0.0}


def _scaled(poly: Poly, factor: float) -> Poly:
    if factor == 0.0:
        return {}
    return {monomial: c * factor for monomial, c in poly.items() if c * factor != 0.0}


def _times(left: Poly, right: Poly) -> Poly:
    product: Poly = {}
    for m1, c1 in left.items():
        for m2, c2 in right.items():
            monomial = tuple(sorted(m1 + m2))
            product[monomial] = product.get(monomial, 0.0) + c1 * c2
    return {monomial: c for monomial, c in product.items() if c != 0.0}


def _dot(left: Sequence[Poly], right: Sequence[Poly]) -> Poly:
    return _plus(*(_times(a, b) for a, b in zip(left, right) if a and b))


def _constant_of(poly: Poly) -> float | None:
    """The value of a constant polynomial (0.0 for the empty one), else None."""
    if not poly:
        return 0.0
    if len(poly) == 1 and () in poly:
        return poly[()]
    return None


def _trivial(poly: Poly) -> bool:
    """Whether ``poly`` is a constant or one name as it is (nothing to compute)."""
    if _constant_of(poly) is not None:
        return True
    if len(poly) == 1:
        ((monomial, coefficient),) = poly.items()
        return coefficient == 1.0 and len(monomial) == 1
    return False


def _render(poly: Poly) -> str:
    """Python source of ``poly`` (terms left to right, a constant term last)."""
    terms = []
    for monomial, coefficient in sorted(poly.items(), key=lambda item: item[0] == ()):
        if not monomial:
            terms.append(repr(coefficient))
        elif coefficient == 1.0:
            terms.append('*'.join(monomial))
        elif coefficient == -1.0:
            terms.append('-' + '*'.join(monomial))
        else:
            terms.append(f'{coefficient!r}*' + '*'.join(monomial))
    if not terms:
        return '0.0'
    text = terms[0]
    for term in terms[1:]:
        text += f' - {term[1:]}' if term.startswith('-') else f' + {term}'
    return text


class _Source:
    """The body of a generated function: one assignment per named value (module docstring).

    :meth:`named` gives a polynomial a name unless it is a constant or a name already; the same
    polynomial gets the same name every time (a value is computed once), and the parts it
    shares with others can get names of their own."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self._names: dict[str, str] = {}

    def named(self, poly: Poly, prefix: str = 't', shared: bool = False) -> Poly:
        """``poly`` as a name (or as it is: a constant or a name). ``shared``: the parts
        other values are likely to have too get names of their own, the terms of degree two
        (from a family's Hessian and the drift, the same for each of its barriers), then all
        but the constant (barriers that differ in their offsets only)."""
        if _trivial(poly):
            return poly
        if shared:
            nonlinear = {m: c for m, c in poly.items() if len(m) >= 2}
            if nonlinear and len(nonlinear) < len(poly):
                poly = _plus(self.named(nonlinear),
                             {m: c for m, c in poly.items() if len(m) < 2})
            if () in poly and len(poly) > 1:
                rest = {m: c for m, c in poly.items() if m != ()}
                if not _trivial(rest):
                    poly = _plus(self.named(rest), _constant(poly[()]))
        text = _render(poly)
        name = self._names.get(text)
        if name is None:
            name = f'{prefix}{len(self._names)}'
            self._names[text] = name
            self.lines.append(f'{name} = {text}')
        return _atom(name)

    def known(self, line: str) -> None:
        """Take an assignment ``name = text`` of inlined source as the value of ``text``."""
        name, equals, text = line.partition(' = ')
        if equals and name.isidentifier() and not line.startswith((' ', 'if ', 'else')):
            self._names.setdefault(text, name)

    def call(self, text: str) -> str:
        """The name of a call's value (``cos(x2)``), computed once."""
        name = self._names.get(text)
        if name is None:
            name = f'c{len(self._names)}'
            self._names[text] = name
            self.lines.append(f'{name} = {text}')
        return name

    def fresh(self, prefix: str) -> str:
        """A new name, for a value assigned by raw lines."""
        name = f'{prefix}{len(self._names)}'
        self._names[f'<{name}>'] = name
        return name


class _Drift:
    """The system's f, J and g as polynomials of its source's names, with J f and the rows
    of J^2 named on first use (shared by every barrier)."""

    def __init__(self, drift: DriftSource, code: _Source) -> None:
        self.n_x = len(drift.f)
        self.f = [_entry(e) for e in drift.f]
        self.jacobian = [[{} for _ in range(self.n_x)] for _ in range(self.n_x)]
        for (i, j), entry in drift.jacobian.items():
            self.jacobian[i][j] = _entry(entry)
        self.g = [[{} for _ in range(drift.n_u)] for _ in range(self.n_x)]
        for (i, j), entry in drift.g.items():
            self.g[i][j] = _entry(entry)
        self._code = code
        self._jf: list[Poly] | None = None
        self._square: dict[int, list[Poly]] = {}

    def jf(self) -> list[Poly]:
        """J f, entry by entry."""
        if self._jf is None:
            self._jf = [self._code.named(_dot(row, self.f)) for row in self.jacobian]
        return self._jf

    def square_row(self, i: int) -> list[Poly]:
        """Row i of J^2."""
        if i not in self._square:
            row = self.jacobian[i]
            self._square[i] = [
                self._code.named(_plus(*(_times(row[j], self.jacobian[j][k])
                                         for j in range(self.n_x) if row[j])))
                for k in range(self.n_x)]
        return self._square[i]


def _quadratic_rows(code: _Source, drift: _Drift, x: list[Poly], rows: QuadraticRows,
                    gammas: Sequence[float]) -> list[tuple[Poly, list[Poly]]]:
    """(h, grad h) of each row of ``rows`` at the top of its cascade (module docstring)."""
    beta = _cascade_weights(gammas)
    levels = len(gammas) + 1
    n_x = drift.n_x
    out = []
    for constant, linear, hessian in zip(rows.constant, rows.linear, rows.hessian):
        linear = [float(v) for v in linear]
        hessian = [[float(v) for v in row] for row in hessian]

        def q_times(vector: list[Poly], hessian: list[list[float]] = hessian) -> list[Poly]:
            return [_plus(*(_scaled(vector[j], q) for j, q in enumerate(row) if q))
                    for row in hessian]

        # g0 = a + Q x = grad L^0 h, then the blocks C_l in terms of it (the last is g0)
        g0 = [_plus(_constant(a), qx) for a, qx in zip(linear, q_times(x))]
        qf = q_times(drift.f) if levels >= 2 else []
        qjf = q_times(drift.jf()) if levels >= 3 else []
        if levels == 1:
            blocks = [g0]
        elif levels == 2:
            blocks = [[_plus(_scaled(g, beta[0]), _scaled(v, beta[1])) for g, v in zip(g0, qf)],
                      g0]
        else:
            blocks = [[_plus(_scaled(g, beta[0]), _scaled(v, beta[1]), _scaled(w, beta[2]))
                       for g, v, w in zip(g0, qf, qjf)],
                      [_plus(_scaled(g, beta[1]), _scaled(v, 2.0 * beta[2]))
                       for g, v in zip(g0, qf)],
                      g0]
        grad = list(blocks[0])
        for level, block in enumerate(blocks[1:], start=1):
            for i, c in enumerate(block):
                if not c:
                    continue
                power = drift.jacobian[i] if level == 1 else drift.square_row(i)
                for k in range(n_x):
                    if power[k]:
                        grad[k] = _plus(grad[k], _times(c, power[k]))
        # h_top = beta_0 c + a^T (beta_0 x + beta_1 f + beta_2 J f) + beta_0 1/2 x^T Q x
        #         + beta_1 x^T Q f + beta_2 (f^T Q f + x^T Q J f): the point in parentheses is
        # the same for every barrier with these gains, the terms of Q for the whole family
        parts = [x, drift.f, drift.jf() if levels >= 3 else []][:levels]
        h = _plus(_constant(beta[0] * float(constant)), _scaled(_dot(x, q_times(x)),
                                                                0.5 * beta[0]))
        if levels >= 2:
            h = _plus(h, _scaled(_dot(x, qf), beta[1]))
        if levels >= 3:
            h = _plus(h, _scaled(_plus(_dot(drift.f, qf), _dot(x, qjf)), beta[2]))
        for j, a in enumerate(linear):
            if a:
                point = code.named(_plus(*(_scaled(part[j], weight)
                                           for part, weight in zip(parts, beta))))
                h = _plus(h, _scaled(point, a))
        out.append((h, grad))
    return out


def _lookahead_rows(code: _Source, family: CircleObstacles, n_x: int
                    ) -> list[tuple[Poly, list[Poly]]]:
    """(h, grad h) of an uncascaded look-ahead circle family, with the point chosen as in
    :func:`~rcbf_ros.core.rcbf.barrier_terms` (module docstring)."""
    i, j = family.position_indices
    heading = family.heading_index
    lookahead = float(family.lookahead)
    cos = _atom(code.call(f'cos(x{heading})'))
    sin = _atom(code.call(f'sin(x{heading})'))
    obstacles = [(float(cx), float(cy), float(radius + family.margin) ** 2)
                 for (cx, cy), radius in zip(family.centers, family.radii)]
    if family.speed_input is None:
        offset = _constant(lookahead)
    else:
        # the point behind, where the proposal reverses and that point is clear of every
        # obstacle: ||p - c||^2 - delta^2 >= 0 for each, as barrier_terms compares
        name, bx, by = code.fresh('o'), code.fresh('t'), code.fresh('t')
        clear = ' and '.join(
            f'({bx} - {cx!r})*({bx} - {cx!r}) + ({by} - {cy!r})*({by} - {cy!r}) - {d2!r} >= 0.0'
            for cx, cy, d2 in obstacles)
        code.lines += [f'{name} = {lookahead!r}',
                       f'if u{family.speed_input} < 0.0:',
                       f'    {bx} = x{i} + {-lookahead!r}*{_render(cos)}',
                       f'    {by} = x{j} + {-lookahead!r}*{_render(sin)}',
                       f'    if {clear}:',
                       f'        {name} = {-lookahead!r}']
        offset = _atom(name)
    px = code.named(_plus(_atom(f'x{i}'), _times(offset, cos)))
    py = code.named(_plus(_atom(f'x{j}'), _times(offset, sin)))
    turn_x = code.named(_scaled(_times(offset, sin), -2.0))  # 2 dp/dth
    turn_y = code.named(_scaled(_times(offset, cos), 2.0))
    out = []
    for cx, cy, d2 in obstacles:
        dx = code.named(_plus(px, _constant(-cx)))
        dy = code.named(_plus(py, _constant(-cy)))
        h = _plus(_times(dx, dx), _times(dy, dy), _constant(-d2))
        grad: list[Poly] = [{} for _ in range(n_x)]
        grad[i] = _plus(grad[i], _scaled(dx, 2.0))
        grad[j] = _plus(grad[j], _scaled(dy, 2.0))
        grad[heading] = _plus(grad[heading], _times(dx, turn_x), _times(dy, turn_y))
        out.append((h, grad))
    return out


def _closed_form_families(problem: RCBFProblem
                          ) -> list[tuple[BarrierFamily, tuple[float, ...]]] | None:
    """(base family, cascade gains) of every family, or None where the problem has no closed
    form (module docstring)."""
    system = problem.system
    if type(system) not in CLOSED_FORM_SYSTEMS:
        return None
    parts = []
    for family in problem.families:
        base, levels = unwrap_cascades(family)
        if type(base) not in _QUADRATIC_FAMILIES or len(levels) > MAX_CASCADE_DEPTH:
            return None
        if any(level.system != system or type(level.system) is not type(system)
               for level in levels):
            return None
        if type(base) is CircleObstacles and base.has_lookahead and levels:
            return None
        parts.append((base, tuple(float(level.gamma) for level in levels)))
    return parts


def has_closed_form(problem: RCBFProblem) -> bool:
    """Whether ``problem`` has a closed form (module docstring), without generating it."""
    return _closed_form_families(problem) is not None


def _row_terms(problem: RCBFProblem, code: _Source
               ) -> tuple[_Drift, list[tuple[Poly, list[Poly]]]] | None:
    """The drift and (h, grad h) of every row in the problem's order, their lines in ``code``."""
    parts = _closed_form_families(problem)
    if parts is None:
        return None
    system = problem.system
    n_x = system.n_x
    source = system.closed_form_source()
    code.lines += list(source.lines)
    for line in source.lines:
        code.known(line)
    drift = _Drift(source, code)
    x = [_atom(name) for name in state_names(n_x)]
    rows = []
    for base, gammas in parts:
        if type(base) is CircleObstacles and base.has_lookahead:
            rows += _lookahead_rows(code, base, n_x)
        else:
            rows += _quadratic_rows(code, drift, x, base.quadratic_rows(n_x), gammas)
    return drift, rows


def _compiled(code: _Source, arguments: str, n_x: int, n_u: int, name: str,
              returned: str, constants: dict | None = None) -> tuple[Callable, str]:
    """The function of ``code`` (arguments: lists of floats, unpacked into named floats;
    ``constants``: more names for it to read)."""
    unpack = {'x': state_names(n_x), 'u': [f'u{j}' for j in range(n_u)],
              'mean': [f'm{k}' for k in range(n_x)], 'std': [f's{k}' for k in range(n_x)]}
    source = '\n'.join([f'def {name}({arguments}):',
                        *(f'    {", ".join(unpack[a])}, = {a}' for a in arguments.split(', ')),
                        *(f'    {line}' for line in code.lines),
                        f'    return {returned}', ''])
    namespace = dict(SOURCE_NAMESPACE, **(constants or {}))
    exec(compile(source, f'<closed form: {name}>', 'exec'), namespace)  # noqa: S102
    return namespace[name], source


def _lie(code: _Source, drift: _Drift, grad: list[Poly]) -> tuple[Poly, list[Poly]]:
    """L_f h and the (named) entries of L_g h of one row."""
    lf = _dot(grad, drift.f)
    lg = [code.named(_dot(grad, [row[j] for row in drift.g]), 'l')
          for j in range(len(drift.g[0]))]
    return lf, lg


class ClosedFormTerms:
    """h, grad h, L_f h and L_g h of one state for a problem with a closed form, generated
    for the problem (module docstring); build with :meth:`from_problem`."""

    def __init__(self, evaluate: Callable, source: str, n_u: int) -> None:
        self._evaluate = evaluate
        self._no_proposal = [0.0] * n_u  # picks the point ahead
        self.source = source
        """The generated function's source."""

    @classmethod
    def from_problem(cls, problem: RCBFProblem) -> ClosedFormTerms | None:
        """The closed form of ``problem``'s terms, or None where it has none (module
        docstring)."""
        code = _Source()
        found = _row_terms(problem, code)
        if found is None:
            return None
        drift, rows = found
        outputs = []
        for h, grad in rows:
            grad = [code.named(v, 'g') for v in grad]
            lf, lg = _lie(code, drift, grad)
            outputs.append([_render(code.named(h, 'h')), [_render(v) for v in grad],
                            _render(code.named(lf, 'f')), [_render(v) for v in lg]])
        returned = ', '.join(
            '[' + ', '.join(('[' + ', '.join(row[part]) + ']') if isinstance(row[part], list)
                            else row[part] for row in outputs) + ']' for part in range(4))
        evaluate, source = _compiled(code, 'x, u', problem.system.n_x, problem.system.n_u,
                                     'barrier_terms', returned)
        return cls(evaluate, source, problem.system.n_u)

    def terms(self, x: np.ndarray, u_rl: np.ndarray | None = None) -> NumpyTerms:
        """Barrier terms at x: (n_x,); u_rl: (n_u,) picks the look-ahead point of obstacles with
        a ``speed_input`` (None: the point ahead), as in :func:`barrier_terms`."""
        x_list = np.asarray(x, dtype=np.float64).tolist()
        u_list = (np.asarray(u_rl, dtype=np.float64).tolist() if u_rl is not None
                  else self._no_proposal)
        h, grad, lf, lg = self._evaluate(x_list, u_list)
        return NumpyTerms(np.array(h), np.array(grad).reshape(len(h), len(x_list)),
                          np.array(lf), np.array(lg).reshape(len(h), -1))


RowAssembly = Callable[[list, list, list, list], tuple[list, list, list, float]]
"""(x, u_rl, mean, std), each a list of floats -> (h (K floats), the rows of G (nc lists of
n_u + 1 floats: K RCBF rows [-L_g h_i, -1], then the limit rows), its right-hand side (nc
floats), the sum of the squares of all three (for the filter's data check)): the per-call
constraint assembly of the filter, on every path (the rows of a list may be shared between
calls: they are read, never changed)."""


class ClosedFormAssembly:
    """The filter's per-call constraint assembly in closed form: G and h of
    :meth:`RCBFProblem.qp` at one state, generated for the problem; build with
    :meth:`from_problem`."""

    def __init__(self, evaluate: RowAssembly, source: str) -> None:
        self.evaluate = evaluate
        """(x, u_rl, mean, std) -> (h, rows, upper, sum of squares) (:data:`RowAssembly`)."""
        self.source = source
        """The generated function's source."""

    @classmethod
    def from_problem(cls, problem: RCBFProblem) -> ClosedFormAssembly | None:
        """The closed-form assembly, or None where the problem has no closed form (module
        docstring)."""
        code = _Source()
        found = _row_terms(problem, code)
        if found is None:
            return None
        drift, rows = found
        n_x, n_u = problem.system.n_x, problem.system.n_u
        alpha, k_c = float(problem.alpha), float(problem.k_c)
        named = []
        for h, grad in rows:
            grad = [code.named(v, 'g', shared=True) for v in grad]
            named.append((code.named(h, 'h', shared=True), grad, *_lie(code, drift, grad)))
        # The right-hand side L_f h + L_g h u + alpha h + rho is grad h^T (x_dot + psi) +
        # alpha h with x_dot = f + g u, the nominal motion at the proposal, and psi the vertex
        # of the box where rho = min grad h^T psi is attained: psi_k = mean_k - k_c std_k
        # sign(grad_k) (qp.robust_margin). The two candidates x_dot_k + psi_k of each entry
        # are computed once for all rows (one where k_c = 0).
        used = sorted({k for _, grad, _, _ in named for k, v in enumerate(grad) if v})
        for k in used:
            motion = _plus(drift.f[k], *(_times(entry, _atom(f'u{j}'))
                                         for j, entry in enumerate(drift.g[k]) if entry),
                           _atom(f'm{k}'))
            code.lines.append(f'lo{k} = {_render(_plus(motion, _scaled(_atom(f"s{k}"), -k_c)))}')
            if k_c != 0.0:
                code.lines.append(
                    f'hi{k} = {_render(_plus(motion, _scaled(_atom(f"s{k}"), k_c)))}')
        h_out, rows_out, upper_out, squares = [], [], [], []
        for h, grad, _, lg in named:
            vertex: list[Poly] = []
            for k, v in enumerate(grad):
                value = _constant_of(v)
                if not v:
                    vertex.append({})
                elif k_c == 0.0:
                    vertex.append(_atom(f'lo{k}'))
                elif value is None:
                    vertex.append(_atom(f'(lo{k} if {_render(v)} >= 0.0 else hi{k})'))
                else:
                    vertex.append(_atom(f'lo{k}' if value >= 0.0 else f'hi{k}'))
            upper = code.named(_plus(_dot(grad, vertex), _scaled(h, alpha)), 'b')
            h_out.append(_render(h))
            rows_out.append('[' + ', '.join(
                [_render(_scaled(v, -1.0)) for v in lg] + ['-1.0']) + ']')
            upper_out.append(_render(upper))
            # the data's sum of squares: h, the row (-L_g h, -1) and its right-hand side
            squares.append(_plus(*(_times(v, v) for v in (h, *lg, upper)), _constant(1.0)))
        # the limit rows: [e_j, 0] z <= u_max_j - u_j, then [-e_j, 0] z <= u_j - u_min_j
        constants = {}
        if problem.has_limits:
            system = problem.system
            unit = np.eye(n_u, n_u + 1)
            for j, row in enumerate((np.concatenate((unit, -unit)) + 0.0).tolist()):
                constants[f'limit{j}'] = row  # the same list every call (never changed)
                rows_out.append(f'limit{j}')
                squares.append(_constant(1.0))
            for j in range(n_u):
                limit = _plus(_constant(float(system.u_max[j])), _scaled(_atom(f'u{j}'), -1.0))
                upper_out.append(_render(limit))
                squares.append(_times(limit, limit))
            for j in range(n_u):
                limit = _plus(_atom(f'u{j}'), _constant(-float(system.u_min[j])))
                upper_out.append(_render(limit))
                squares.append(_times(limit, limit))
        code.lines.append(f'size = {_render(_plus(*squares))}')
        returned = (f'[{", ".join(h_out)}], [{", ".join(rows_out)}], '
                    f'[{", ".join(upper_out)}], size')
        evaluate, source = _compiled(code, 'x, u, mean, std', n_x, n_u, 'rcbf_rows', returned,
                                     constants)
        return cls(evaluate, source)


def state_barrier_values(problem: RCBFProblem, states: np.ndarray) -> np.ndarray:
    """:meth:`RCBFProblem.state_h` of many states, as numpy: where a look-ahead point follows
    the direction of travel, each value is the larger of the point ahead's and the point
    behind's. In closed form where the problem has one (no torch); otherwise through
    ``state_h`` in batches (torch imported here).

    Args:
        states: (N, n_x) float64 states.

    Returns:
        (N, K) barrier values.
    """
    states = np.asarray(states, dtype=np.float64).reshape(-1, problem.system.n_x)
    shape = (len(states), problem.n_barriers)
    closed_form = ClosedFormTerms.from_problem(problem)
    if closed_form is None:
        from rcbf_ros.core.torch_import import load_torch
        torch = load_torch()
        stacked = torch.from_numpy(np.ascontiguousarray(states))
        return np.concatenate([np.zeros((0, shape[1]))] + [
            problem.state_h(chunk).numpy() for chunk in torch.split(stacked, 4096)])
    speeds = sorted({s for s in (getattr(f, 'speed_input', None) for f in problem.families)
                     if s is not None})
    backwards = None
    if speeds:
        backwards = np.zeros(problem.system.n_u)
        backwards[speeds] = -1.0
    rows = []
    for x in states:
        h = closed_form.terms(x).h
        if backwards is not None:
            h = np.maximum(h, closed_form.terms(x, backwards).h)
        rows.append(h)
    return np.array(rows, dtype=np.float64).reshape(shape)
