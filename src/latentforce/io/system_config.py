"""Stage 2 of :mod:`latentforce.io.config` for ``[system]``: the system object of each type
(linear SDOF, matrices, a shear frame's lists, duffing, bouc-wen, ``[[system.elements]]`` on a
linear structure), with its parameters sorted into fixed numbers and priors, and a
one-paragraph error naming the key for every physically invalid value."""

from __future__ import annotations

from latentforce.io.matrices import _check_psd, _matrix
from latentforce.io.params import _split
from latentforce.io.schema import _did_you_mean, _Fail, _SystemSection
from latentforce.systems import (
    DEFAULT_BOUC_WEN_SUBSTEPS,
    ELEMENT_KEYS,
    SYSTEM_TYPES,
    BoucWen,
    Duffing,
    Element,
    LinearSystem,
    NonlinearMDOF,
    ShearFrame,
    element_param,
)

# In the interface but without an implementation yet.
PLANNED_SYSTEM_TYPES: tuple[str, ...] = ()
BOUC_WEN_KEYS = ("alpha", "beta", "gamma", "nu")
#: what a fixed value of each scalar system key must be (io/params._scalar); an "any" key may be
#: inferred with either sign under a normal prior (latentforce.priors.SignedNormal), any other
#: prior keeps it positive
SCALAR_RULES = {
    "m": "positive",
    "c": "nonnegative",
    "k": "positive",
    "k3": "any",
    "alpha": "nonnegative",
    "beta": "any",
    "gamma": "any",
    "nu": "exponent",
}


def _system(fail: _Fail, s: _SystemSection, fixed: dict, free: dict):
    """Build the system object and sort its parameters into fixed and free."""
    if s.type in PLANNED_SYSTEM_TYPES:
        raise fail(
            "[system].type",
            f"system type {s.type!r} is not available yet; available system types: {', '.join(SYSTEM_TYPES)}.",
        )
    if s.type not in SYSTEM_TYPES:
        raise fail(
            "[system].type",
            f"unknown system type {s.type!r}"
            f"{_did_you_mean(s.type, SYSTEM_TYPES + PLANNED_SYSTEM_TYPES, '{!r}')} "
            f"Available system types: {', '.join(SYSTEM_TYPES)}.",
        )
    given = {
        n
        for n in ("m", "c", "k", "k3", "M", "C", "K", "masses", "dampings", "stiffnesses", "force_dofs")
        + BOUC_WEN_KEYS
        + ("substeps",)
        if getattr(s, n) is not None
    }
    if s.steps_per_sample != "auto":
        given.add("steps_per_sample")

    def require(names):
        for n in names:
            if getattr(s, n) is None:
                raise fail(f"[system].{n}", f"is required for a {s.type} system.")

    def refuse(names, why):
        for n in names:
            if n in given:
                raise fail(f"[system].{n}", why)

    def scalars(names):
        for n in names:
            _split(fail, f"[system].{n}", n, getattr(s, n), SCALAR_RULES[n], fixed, free)

    matrix_keys = ("M", "C", "K", "masses", "dampings", "stiffnesses", "force_dofs")
    if s.elements is not None and s.type != "linear":
        raise fail(
            "[[system.elements]]",
            'nonlinear elements go with type = "linear": give the structure\'s linear part (M, C, K, or '
            "masses, dampings and stiffnesses, or m, c, k) and the elements make it nonlinear; a "
            f"{s.type} system is a single DOF with its own nonlinearity.",
        )
    if s.type == "duffing":
        refuse(matrix_keys, "a duffing system is single-DOF: give m, c, k and k3.")
        refuse(BOUC_WEN_KEYS, 'alpha, beta, gamma and nu belong to a bouc-wen system; use type = "bouc-wen".')
        require(("m", "c", "k", "k3"))
        scalars(("m", "c", "k", "k3"))
        return Duffing(substeps=s.substeps or 1)
    if s.type == "bouc-wen":
        refuse(matrix_keys, "a bouc-wen system is single-DOF: give m, c, k, alpha, beta, gamma and nu.")
        refuse(("k3",), 'k3 (cubic stiffness) belongs to a duffing system; use type = "duffing".')
        require(("m", "c", "k") + BOUC_WEN_KEYS)
        scalars(("m", "c", "k") + BOUC_WEN_KEYS)
        return BoucWen(substeps=s.substeps or DEFAULT_BOUC_WEN_SUBSTEPS)

    refuse(("k3",), 'k3 (cubic stiffness) belongs to a duffing system; use type = "duffing".')
    refuse(BOUC_WEN_KEYS, 'alpha, beta, gamma and nu belong to a bouc-wen system; use type = "bouc-wen".')
    base = _linear_structure(fail, s, given, fixed, free, refuse, require, scalars)
    if s.elements is not None:
        return _with_elements(fail, s, base, fixed, free)
    refuse(
        ("substeps", "steps_per_sample"),
        "substeps and steps_per_sample apply to nonlinear systems (duffing, bouc-wen, [[system.elements]]); "
        "a linear one is discretised exactly.",
    )
    return base


def _linear_structure(fail: _Fail, s: _SystemSection, given: set, fixed: dict, free: dict, refuse, require, scalars):
    """The linear system of ``[system]``: m, c, k, or matrices M, C, K, or a shear frame's lists."""
    frame = given & {"masses", "dampings", "stiffnesses"}
    if frame:
        return _shear_frame(fail, s, given, fixed, free, refuse, require)
    matrices = given & {"M", "C", "K"}
    if not matrices:  # linear SDOF
        require(("m", "c", "k"))
        if s.force_dofs is not None and s.force_dofs != [0]:
            raise fail("[system].force_dofs", f"a single-DOF system has only DOF 0, got {s.force_dofs}.")
        scalars(("m", "c", "k"))
        return LinearSystem(ndof=1, force_dofs=(0,))

    # Linear MDOF: matrices are fixed numbers in this version.
    refuse(("m", "c", "k"), "give either scalars m, c, k (one DOF) or matrices M, C, K, not both.")
    require(("M", "C", "K"))
    M, C, K = (_matrix(fail, f"[system].{n}", getattr(s, n)) for n in ("M", "C", "K"))
    n = M.shape[0]
    for name, A in (("C", C), ("K", K)):
        if A.shape != M.shape:
            raise fail(
                f"[system].{name}",
                f"is {A.shape[0]}x{A.shape[0]} but M is {n}x{n}; all three matrices must have the same size.",
            )
    _check_psd(fail, "[system].M", M, "mass", definite=True)
    _check_psd(fail, "[system].K", K, "stiffness", definite=False)
    # Damping need not be symmetric, but it must dissipate energy.
    _check_psd(fail, "[system].C", 0.5 * (C + C.T), "damping (symmetric part of the)", definite=False)
    _check_force_dofs(fail, s.force_dofs, n)
    if n == 1:
        # One DOF in matrix form: the model reads scalars m, c, k.
        fixed.update(m=float(M[0, 0]), c=float(C[0, 0]), k=float(K[0, 0]))
    else:
        fixed.update(M=M, C=C, K=K)
    return LinearSystem(ndof=n, force_dofs=tuple(s.force_dofs if s.force_dofs is not None else [0]))


def _with_elements(fail: _Fail, s: _SystemSection, base, fixed: dict, free: dict) -> NonlinearMDOF:
    """``[[system.elements]]`` on the linear structure ``base``: DOFs inside the structure, each
    element's keys (a number or a prior, as ``element<e>_<key>``), no element given twice."""
    n = base.ndof
    if not s.elements:
        raise fail("[[system.elements]]", "is empty: give at least one element, or leave the key out.")
    seen: dict[tuple, int] = {}
    elements = []
    for e, el in enumerate(s.elements):
        where = f"[[system.elements]][{e}]"
        for d in el.dofs:
            if d >= n:
                valid = "only DOF 0" if n == 1 else f"DOFs 0..{n - 1}"
                raise fail(f"{where}.dofs", f"DOF {d} is outside the structure, which has {valid}.")
        if len(el.dofs) == 2 and el.dofs[0] == el.dofs[1]:
            raise fail(
                f"{where}.dofs",
                f"joins DOF {el.dofs[0]} to itself: give two different DOFs, or [{el.dofs[0]}] alone for an "
                "element to the ground.",
            )
        pair = (el.type, frozenset(el.dofs))
        if pair in seen:
            raise fail(
                f"{where}.dofs",
                f"element {seen[pair]} is also a {el.type} element on DOFs {sorted(el.dofs)}: two such elements "
                "act as one and their parameters cannot be told apart; give one element.",
            )
        seen[pair] = e
        keys = ELEMENT_KEYS[el.type]
        for kind, other in ELEMENT_KEYS.items():
            for key in other:
                if kind != el.type and key not in keys and getattr(el, key) is not None:
                    raise fail(f"{where}.{key}", f"{key} belongs to a {kind} element; this one is {el.type}.")
        for key in keys:
            value = getattr(el, key)
            if value is None:
                raise fail(f"{where}.{key}", f"is required for a {el.type} element (keys: {', '.join(keys)}).")
            name = element_param(e, key)
            _split(fail, f"{where}.{key}", name, value, SCALAR_RULES[key], fixed, free)
        elements.append(Element(el.type, tuple(el.dofs)))
    hysteretic = any(e.kind == "bouc-wen" for e in elements)
    substeps = s.substeps or (DEFAULT_BOUC_WEN_SUBSTEPS if hysteretic else 1)
    return NonlinearMDOF(base, elements, substeps=substeps)


def _check_force_dofs(fail: _Fail, force_dofs: list[int] | None, n: int) -> None:
    force_dofs = force_dofs if force_dofs is not None else [0]
    if not force_dofs:
        raise fail("[system].force_dofs", "must list at least one DOF.")
    for d in force_dofs:
        if not 0 <= d < n:
            raise fail("[system].force_dofs", f"DOF {d} is outside the system's DOFs 0..{n - 1}.")
    if len(set(force_dofs)) != len(force_dofs):
        raise fail("[system].force_dofs", f"lists a DOF more than once: {force_dofs}.")


def _shear_frame(fail: _Fail, s: _SystemSection, given: set, fixed: dict, free: dict, refuse, require):
    """A shear frame: one mass per floor and one damper and spring per storey, each a number
    or a prior table (parameters ``m_i``, ``c_i``, ``k_i``)."""
    refuse(
        ("m", "c", "k", "M", "C", "K"),
        "give a shear frame's floors and storeys as lists (masses, "
        "dampings, stiffnesses), or matrices M, C, K, not both.",
    )
    require(("masses", "dampings", "stiffnesses"))
    n = len(s.masses)
    for key in ("dampings", "stiffnesses"):
        if len(getattr(s, key)) != n:
            raise fail(
                f"[system].{key}",
                f"has {len(getattr(s, key))} entries but masses has {n}: "
                "a shear frame has one mass per floor and one damper and "
                "one spring per storey (storey i joins floor i to floor i-1, "
                "storey 0 to the ground).",
            )
    if n < 1:
        raise fail("[system].masses", "must list at least one floor mass.")
    for key, short, rule in (
        ("masses", "m", "positive"),
        ("dampings", "c", "nonnegative"),
        ("stiffnesses", "k", "positive"),
    ):
        for i, value in enumerate(getattr(s, key)):
            _split(fail, f"[system].{key}[{i}]", f"{short}_{i}", value, rule, fixed, free)
    _check_force_dofs(fail, s.force_dofs, n)
    return ShearFrame(ndof=n, force_dofs=tuple(s.force_dofs if s.force_dofs is not None else [0]))
