"""Is a richer model's fit significantly better? The F-test of nested least squares.

The non-central thick lens adds two pupil terms (`c1`, `c2`) to the central one, whose
optimum is its start. Where the lens is a central camera to the data's precision (long
lenses), those two terms fit noise and are not determined: measured, they reached
`c2` = 6.7e6 mm on a 99.5 mm double Gauss and made distances up to 28 % worse than the
central model. The calibration therefore keeps them only where they reduce the residual
sum of squares by more than noise would.

With `RSS₀` the reduced model's (terms held at zero) and `RSS₁` the full model's, `q`
extra parameters and `d` = observations − free parameters of the full model,

    F = ((RSS₀ − RSS₁) / q) / (RSS₁ / d)

is F(q, d)-distributed when the extra terms are zero and the residuals are Gaussian
(the residuals' scale cancels: a wrong σ does not change the test). For even q its tail
is closed form (the regularised incomplete beta function with an integer second
argument): with `x = d / (d + q f)` and `a = d / 2`,

    P(F > f) = x^a · Σ_{j < q/2} [Γ(a + j) / (Γ(a) j!)] (1 − x)^j,

which for q = 2 is `(1 + 2 f / d)^(−d/2)`. The non-central camera tests its axial pupil
terms (`c1`, `c2`) and its lateral offset (`ax`, `ay`) together against the central
optimum (q = 4; q = 2 where a user froze one pair), then, where those are kept, its
pivot terms (`b1`, `b2`) against that optimum (q = 2).
"""

from __future__ import annotations

import dataclasses
import math

__all__ = ["NestedTest", "nested_f_test"]

#: Significance level below which the extra terms are kept.
ALPHA = 1e-3


@dataclasses.dataclass(frozen=True)
class NestedTest:
    """The F-test of `q` extra parameters.

    **Fields:** `f` (the statistic), `p_value` (its upper tail under the reduced
    model), `q`, `dof` (d), `significant` (`p_value < alpha`), `alpha`.
    """

    f: float
    p_value: float
    q: int
    dof: int
    significant: bool
    alpha: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def nested_f_test(
    rss_reduced: float, rss_full: float, n_observations: int, n_free_full: int, q: int,
    *, alpha: float = ALPHA,
) -> NestedTest:  # fmt: skip
    """F-test of a full model with `q` (even) more free parameters than the reduced one.

    **Arguments:** the residual sums of squares (weighted, `2 · Fit.cost`) of the
    reduced and the full model at their optima, the number of residuals, the full
    model's free parameters, `q`, and the significance level.

    **Returns:** a [`NestedTest`][]. A full fit that is worse than the reduced one (an
    optimiser that stopped early) gives `f = 0`, `p_value = 1`: not significant.
    """
    if q < 2 or q % 2:
        raise ValueError(f"the closed-form tail is for an even q >= 2 extra parameters, "
                         f"got q = {q}")  # fmt: skip
    dof = int(n_observations) - int(n_free_full)
    if dof < 1:
        raise ValueError(f"no degrees of freedom left ({n_observations} residuals, "
                         f"{n_free_full} free parameters)")  # fmt: skip
    if not (math.isfinite(rss_reduced) and math.isfinite(rss_full)) or rss_full < 0:
        raise ValueError("the residual sums of squares must be finite and non-negative")
    if rss_full == 0.0:  # exact data: any reduction is significant, none is not
        f = math.inf if rss_reduced > 0.0 else 0.0
    else:
        f = max(0.0, (rss_reduced - rss_full) / q) / (rss_full / dof)
    if f == 0.0:
        p = 1.0
    elif math.isinf(f):
        p = 0.0
    else:
        p = _f_tail_even_q(f, q, dof)
    return NestedTest(float(f), float(p), int(q), dof, bool(p < alpha), float(alpha))


def _f_tail_even_q(f: float, q: int, dof: int) -> float:
    """`P(F(q, dof) > f)` for even `q` (module docstring), summed in logarithms."""
    if q == 2:
        return math.exp(-0.5 * dof * math.log1p(2.0 * f / dof))
    a = 0.5 * dof
    log_x = -math.log1p(q * f / dof)  # x = d / (d + q f)
    one_minus_x = (q * f / dof) / (1.0 + q * f / dof)
    if one_minus_x == 0.0:
        return 1.0
    log_1mx = math.log(one_minus_x)
    terms = [
        math.lgamma(a + j) - math.lgamma(a) - math.lgamma(j + 1.0) + j * log_1mx
        for j in range(q // 2)
    ]
    top = max(terms)
    return min(1.0, math.exp(a * log_x + top + math.log(sum(math.exp(t - top) for t in terms))))
