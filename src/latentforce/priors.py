r"""Prior densities of the inferred parameters, and the maps to the samplers' coordinates.

Most parameters we infer (mass, damping, stiffness, force variance and
lengthscale) are positive. A prior is a density on the physical value
:math:`\theta > 0`; samplers work in the unconstrained space :math:`x` with

.. math:: \theta = \operatorname{softplus}(x) = \log(1 + e^x)

(Eq. 27, ISMA 2018), so the density of :math:`x` carries the Jacobian
:math:`d\theta/dx = \sigma(x)` (the logistic sigmoid):

.. math:: \log p_x(x) = \log p_\theta(\operatorname{softplus}(x)) + \log\sigma(x).

Priors are frozen dataclasses registered as JAX pytrees: their numbers are
leaves, so ``log_prob`` can be jitted, vmapped and differentiated, and two
priors of different families never compare equal (as same-length
NamedTuples would). All share one signature, ``log_prob(theta) -> log
density``, which is ``-inf`` for :math:`\theta \le 0`.

**Signed parameters.** A cubic stiffness ``k3`` (softening springs) and
Bouc-Wen's ``beta`` and ``gamma`` (the Noel-Schoukens benchmark has
:math:`\gamma < 0`) may take either sign. A ``normal`` prior on such a key is
:class:`SignedNormal`, a density on the whole real line, and the samplers'
coordinate is its standardised value :math:`x = (\theta - \text{mean})/\text{sd}`
(:func:`to_value`, :func:`to_coordinate`, :func:`log_prob_coordinate`): an
affine map, so the coordinates have the unit scale that the samplers' first
random-walk steps assume, whatever the parameter's magnitude. Any other prior
kind on a signed key keeps it positive (a user who writes a log-normal prior
for ``k3`` says it is a hardening spring).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
from jax.scipy import stats
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "PRIOR_PARAMS",
    "AtLeast",
    "Flat",
    "Gamma",
    "HalfNormal",
    "LogNormal",
    "Normal",
    "Prior",
    "SignedNormal",
    "SoftplusNormal",
    "log_jacobian_softplus",
    "log_prob_coordinate",
    "log_prob_unconstrained",
    "prior_from_spec",
    "softplus",
    "softplus_inverse",
    "to_coordinate",
    "to_value",
]


# ----- the softplus transform ------------------------------------------------
def softplus(x: ArrayLike) -> Float[Array, "..."]:
    r""":math:`\theta = \log(1 + e^x)`, stable for large :math:`|x|` (Eq. 27, ISMA 2018)."""
    # logaddexp(0, x) = max(0, x) + log1p(exp(-|x|)): no overflow for large x,
    # full relative precision for very negative x.
    return jnp.logaddexp(0.0, jnp.asarray(x, dtype=float))


def softplus_inverse(theta: ArrayLike) -> Float[Array, "..."]:
    r""":math:`x = \log(e^\theta - 1) = \theta + \log(1 - e^{-\theta})` for :math:`\theta > 0`.

    The second form never overflows for large :math:`\theta`, and ``expm1``
    keeps full precision for tiny :math:`\theta` (where
    :math:`e^\theta - 1 \approx \theta`). NaN for :math:`\theta \le 0`.
    """
    theta = jnp.asarray(theta, dtype=float)
    return theta + jnp.log(-jnp.expm1(-theta))


def log_jacobian_softplus(x: ArrayLike) -> Float[Array, "..."]:
    r""":math:`\log\, d\theta/dx = \log \sigma(x) = -\operatorname{softplus}(-x)`, computed stably."""
    return -softplus(-jnp.asarray(x, dtype=float))


# ----- helpers -----------------------------------------------------------------
def _positive(theta: ArrayLike) -> tuple[Array, Array]:
    """``(theta, is_positive)`` with ``theta`` replaced by 1 where it is not positive.

    Evaluating e.g. ``log(theta)`` only at safe points keeps both the value
    and the gradient of the ``where`` below free of NaN.
    """
    theta = jnp.asarray(theta, dtype=float)
    ok = theta > 0
    return jnp.where(ok, theta, 1.0), ok


def _mask(ok: Array, logp: Array) -> Array:
    return jnp.where(ok, logp, -jnp.inf)


def _register(cls):
    """Freeze ``cls`` as a dataclass and register its fields as pytree leaves."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    fields = [f.name for f in dataclasses.fields(cls)]
    return jax.tree_util.register_dataclass(cls, data_fields=fields, meta_fields=[])


class Prior:
    """Common interface: a density on the physical parameter :math:`\\theta > 0`.

    ``log_prob(theta)`` returns the log density (``-inf`` for ``theta <= 0``),
    elementwise over any array shape; ``sample(key, shape)`` draws from it
    (not for improper priors); ``default_init()`` is a sensible starting
    value for a sampler (``None`` where the prior has none). ``signed``: the
    support is the whole real line (:class:`SignedNormal`), not the positive reals.
    """

    name: ClassVar[str] = ""
    signed: ClassVar[bool] = False

    def log_prob(self, theta: ArrayLike) -> Float[Array, "..."]:  # pragma: no cover - abstract
        raise NotImplementedError

    def sample(self, key: Array, shape: tuple[int, ...] = ()) -> Float[Array, "..."]:  # pragma: no cover
        raise NotImplementedError

    def default_init(self) -> float | None:  # pragma: no cover - abstract
        raise NotImplementedError


@_register
class Flat(Prior):
    """Improper flat prior on the positive reals: ``0`` for ``theta > 0``, else ``-inf``."""

    name: ClassVar[str] = "flat"

    def log_prob(self, theta):
        _, ok = _positive(theta)
        return _mask(ok, jnp.zeros_like(ok, dtype=float))

    def sample(self, key, shape=()):
        raise ValueError("the flat prior is improper: it cannot be sampled")

    def default_init(self):
        return None


@_register
class Normal(Prior):
    r"""Normal :math:`N(\text{mean}, \text{sd}^2)` restricted to :math:`\theta > 0`.

    The truncation is not renormalised: the constant does not matter to
    Metropolis and the mass below zero is negligible for sensible priors.
    """

    mean: Any
    sd: Any
    name: ClassVar[str] = "normal"

    def log_prob(self, theta):
        t, ok = _positive(theta)
        return _mask(ok, stats.norm.logpdf(t, self.mean, self.sd))

    def sample(self, key, shape=()):
        # Draw from the truncated normal so that samples respect theta > 0.
        mean, sd = jnp.asarray(self.mean, float), jnp.asarray(self.sd, float)
        z = jax.random.truncated_normal(key, -mean / sd, jnp.inf, shape, dtype=float)
        return mean + sd * z

    def default_init(self):
        return float(self.mean)


@_register
class LogNormal(Prior):
    r"""Log-normal: :math:`\log\theta \sim N(\mu, \sigma^2)`."""

    mu: Any
    sigma: Any
    name: ClassVar[str] = "lognormal"

    def log_prob(self, theta):
        t, ok = _positive(theta)
        log_t = jnp.log(t)
        return _mask(ok, stats.norm.logpdf(log_t, self.mu, self.sigma) - log_t)

    def sample(self, key, shape=()):
        return jnp.exp(self.mu + self.sigma * jax.random.normal(key, shape, dtype=float))

    def default_init(self):
        return math.exp(float(self.mu))


@_register
class HalfNormal(Prior):
    r"""Half-normal: :math:`|N(0, \text{sd}^2)|`, density :math:`2\,\phi(\theta/\text{sd})/\text{sd}`."""

    sd: Any
    name: ClassVar[str] = "halfnormal"

    def log_prob(self, theta):
        t, ok = _positive(theta)
        return _mask(ok, jnp.log(2.0) + stats.norm.logpdf(t, 0.0, self.sd))

    def sample(self, key, shape=()):
        return self.sd * jnp.abs(jax.random.normal(key, shape, dtype=float))

    def default_init(self):
        return float(self.sd)


@_register
class Gamma(Prior):
    r"""Gamma with shape :math:`\alpha` and rate :math:`\beta` (mean :math:`\alpha/\beta`)."""

    shape: Any
    rate: Any
    name: ClassVar[str] = "gamma"

    def log_prob(self, theta):
        t, ok = _positive(theta)
        return _mask(ok, stats.gamma.logpdf(t, self.shape, scale=1.0 / jnp.asarray(self.rate, float)))

    def sample(self, key, shape=()):
        return jax.random.gamma(key, self.shape, shape, dtype=float) / self.rate

    def default_init(self):
        return float(self.shape) / float(self.rate)


@_register
class SoftplusNormal(Prior):
    r"""Normal in the samplers' space:
    :math:`x = \operatorname{softplus}^{-1}(\theta) \sim N(\text{loc}, \text{scale}^2)`.

    The density of :math:`\theta` carries the Jacobian
    :math:`dx/d\theta = 1/(1 - e^{-\theta})`. This is the form a parameter
    takes when its prior is carried over from an earlier run's posterior
    (``prior = "posterior"`` in a config): the posterior draws in the
    softplus space, where the samplers work and posteriors are close to
    Gaussian, fitted by their mean and standard deviation.
    """

    loc: Any
    scale: Any
    name: ClassVar[str] = "softplus-normal"

    def log_prob(self, theta):
        t, ok = _positive(theta)
        x = softplus_inverse(t)
        return _mask(ok, stats.norm.logpdf(x, self.loc, self.scale) - jnp.log(-jnp.expm1(-t)))

    def sample(self, key, shape=()):
        return softplus(self.loc + self.scale * jax.random.normal(key, shape, dtype=float))

    def default_init(self):
        return float(softplus(self.loc))


@_register
class AtLeast(Prior):
    r"""``base`` truncated to :math:`\theta \ge` ``lower``: a parameter whose physics has a lower bound
    above zero (Bouc-Wen's exponent ``nu`` >= 1, below which its rate is not Lipschitz at r = 0).
    The samplers keep their coordinate; a proposal below the bound has log density ``-inf`` and is
    rejected. Unnormalised (the base's mass below the bound is not divided out): the samplers need the
    density up to a constant only."""

    base: Prior
    lower: Any
    name: ClassVar[str] = "at-least"

    def log_prob(self, theta):
        theta = jnp.asarray(theta, dtype=float)
        return jnp.where(theta >= self.lower, self.base.log_prob(theta), -jnp.inf)

    def sample(self, key, shape=(), tries: int = 64):
        """The first of ``tries`` draws of ``base`` at or above the bound (the bound itself where none is)."""
        draws = self.base.sample(key, (tries, *shape))
        ok = draws >= self.lower
        first = jnp.argmax(ok, axis=0)
        pick = jnp.take_along_axis(draws, first[None], axis=0)[0]
        return jnp.where(jnp.any(ok, axis=0), pick, self.lower)

    def default_init(self):
        init = self.base.default_init()
        return None if init is None else max(float(init), float(self.lower))


@_register
class SignedNormal(Prior):
    r"""Normal :math:`N(\text{mean}, \text{sd}^2)` on the whole real line: the ``normal`` prior
    of a parameter that may take either sign (``k3``, ``beta``, ``gamma``; module doc)."""

    mean: Any
    sd: Any
    name: ClassVar[str] = "normal"
    signed: ClassVar[bool] = True

    def log_prob(self, theta):
        return stats.norm.logpdf(jnp.asarray(theta, dtype=float), self.mean, self.sd)

    def sample(self, key, shape=()):
        return self.mean + self.sd * jax.random.normal(key, shape, dtype=float)

    def default_init(self):
        return float(self.mean)


#: Each prior's name in a config file, with its parameter names in order.
PRIOR_PARAMS: dict[str, tuple[str, ...]] = {
    "flat": (),
    "normal": ("mean", "sd"),
    "lognormal": ("mu", "sigma"),
    "halfnormal": ("sd",),
    "gamma": ("shape", "rate"),
}

_PRIOR_CLASSES: dict[str, type] = {
    "flat": Flat,
    "normal": Normal,
    "lognormal": LogNormal,
    "halfnormal": HalfNormal,
    "gamma": Gamma,
}

# Parameters that must be strictly positive (a location may be any real).
_POSITIVE_PARAMS = {"sd", "sigma", "shape", "rate"}


def prior_from_spec(name: str, *, signed: bool = False, **kwargs: float) -> Prior:
    """Build a prior from its config name and keyword parameters.

    ``normal(mean, sd)``, ``lognormal(mu, sigma)``, ``halfnormal(sd)``,
    ``gamma(shape, rate)``, ``flat()``. ``signed``: the parameter may take
    either sign, and a ``normal`` prior is then :class:`SignedNormal` (module
    doc). Raises ``ValueError`` for an unknown name, a missing or unexpected
    keyword, or a non-finite or (for scales and shapes) non-positive value.
    """
    if name not in PRIOR_PARAMS:
        raise ValueError(f"unknown prior {name!r}; valid priors: {', '.join(PRIOR_PARAMS)}")
    expected = PRIOR_PARAMS[name]
    missing = [p for p in expected if p not in kwargs]
    extra = [p for p in kwargs if p not in expected]
    if missing or extra:
        wanted = ", ".join(expected) if expected else "no parameters"
        parts = []
        if missing:
            parts.append(f"missing {', '.join(missing)}")
        if extra:
            parts.append(f"unexpected {', '.join(extra)}")
        raise ValueError(f"prior {name!r} takes {wanted} ({'; '.join(parts)})")
    values = {}
    for p in expected:
        v = kwargs[p]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"prior {name!r}: {p} must be a finite number, got {v!r}")
        if p in _POSITIVE_PARAMS and not v > 0:
            raise ValueError(f"prior {name!r}: {p} must be positive, got {v!r}")
        values[p] = float(v)
    if signed and name == "normal":
        return SignedNormal(**values)
    return _PRIOR_CLASSES[name](**values)


def log_prob_unconstrained(prior: Prior, x: ArrayLike) -> Float[Array, "..."]:
    r"""Log density of the samplers' coordinate :math:`x` of a parameter with ``prior``.

    :math:`\log p_\theta(\operatorname{softplus}(x)) + \log\sigma(x)` (change of
    variables) for a positive parameter; a signed one's affine coordinate as
    :func:`log_prob_coordinate`.
    """
    return log_prob_coordinate(prior, x, "softplus")


# ----- the samplers' coordinates -------------------------------------------------
# ``positive`` names the map of a positive parameter: "softplus" (Eq. 27, ISMA 2018; the
# Kalman samplers) or "log" (pgas's choice, inference/pgas_block.py). A signed prior's
# coordinate is always its standardised value (module doc).
def to_value(prior: Prior, x: ArrayLike, positive: str = "softplus") -> Float[Array, "..."]:
    """The physical value at the samplers' coordinate ``x``."""
    x = jnp.asarray(x, dtype=float)
    if prior.signed:
        return prior.mean + prior.sd * x
    return softplus(x) if positive == "softplus" else jnp.exp(x)


def to_coordinate(prior: Prior, theta: ArrayLike, positive: str = "softplus") -> Float[Array, "..."]:
    """The samplers' coordinate of the physical value ``theta`` (inverse of :func:`to_value`)."""
    theta = jnp.asarray(theta, dtype=float)
    if prior.signed:
        return (theta - prior.mean) / prior.sd
    return softplus_inverse(theta) if positive == "softplus" else jnp.log(theta)


def log_prob_coordinate(prior: Prior, x: ArrayLike, positive: str = "softplus") -> Float[Array, "..."]:
    r""":math:`\log p_\theta(\theta(x)) + \log|d\theta/dx|`: the prior density of the coordinate."""
    x = jnp.asarray(x, dtype=float)
    if prior.signed:
        return prior.log_prob(to_value(prior, x)) + jnp.log(jnp.asarray(prior.sd, dtype=float))
    if positive == "softplus":
        return prior.log_prob(softplus(x)) + log_jacobian_softplus(x)
    return prior.log_prob(jnp.exp(x)) + x
