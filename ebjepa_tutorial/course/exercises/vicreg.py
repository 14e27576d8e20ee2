"""Checkers of chapters 00-01: the variance and covariance terms, the VICReg loss, and the
conversion of the VICReg paper's coefficients to EB-JEPA's."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ... import losses
from .common import Case, ExerciseError, _describe, _run, compare, diagnose, exercise

_ALONG_THE_BATCH = (0, 0, 1, "the batch and the dimension axes of z exchanged",
                    "Here z is (B, D), one row per sample: each dimension's statistics are taken "
                    "over the batch, down the columns (dim 0)")


def _embedding_cases(seed: int = 0) -> list[Case]:
    g = torch.Generator().manual_seed(seed)
    return [
        Case("a random batch z of shape (32, 8)", (torch.randn(32, 8, generator=g),)),
        Case("a collapsed batch (every row the same)", (torch.ones(16, 4),)),
        Case("a batch with std about 3", (3 * torch.randn(64, 5, generator=g),)),
        Case("a batch of 2 rows", (torch.randn(2, 3, generator=g),)),
        Case("a batch with correlated dimensions",
             (torch.randn(40, 1, generator=g) * torch.tensor([[1.0, -2.0, 0.5]]),)),
        Case("a float64 batch (12, 6)", (torch.randn(12, 6, generator=g, dtype=torch.float64),)),
    ]


def _hinge(std: torch.Tensor, gamma: float) -> torch.Tensor:
    return torch.relu(gamma - std).mean()


_VARIANCE_HINTS = (
    "A collapsed encoder gives every input the same embedding: each of the D dimensions then "
    "has no spread over the batch. The term charges each dimension for the spread it lacks "
    "below a target gamma, and nothing once it has enough. Spread here is the standard "
    "deviation of one dimension across the B samples, not across the D numbers of one sample.",
    "v(Z) = (1/D) * sum over j of max(0, gamma - sqrt(Var_j + eps)), where Var_j is the "
    "unbiased variance (divide by B - 1) of column j of z over its B rows. z is (B, D): that "
    "gives D standard deviations, one hinge each, and their mean, a 0-d tensor. eps sits "
    "inside the square root, so a collapsed dimension has std sqrt(eps) and a finite gradient.",
    "std = torch.sqrt(<the variance of z down the batch, one per dimension> + eps)  # (D,)\n"
    "return <the mean over the D dimensions of torch.relu(gamma - std)>  # 0-d",
)

_VARIANCE_SLIPS = [
    ("you used the biased variance (dividing by B); the course uses the unbiased one, which "
     "divides by B - 1 (PyTorch's default for a variance).",
     lambda z, gamma=1.0, eps=1e-4: _hinge((z.var(0, unbiased=False) + eps).sqrt(), gamma)),
    ("eps is missing from the square root: std = sqrt(Var + eps), so that a collapsed "
     "dimension has std sqrt(eps), not 0 (and a finite gradient).",
     lambda z, gamma=1.0, eps=1e-4: _hinge(z.var(0).sqrt(), gamma)),
    ("you added eps after the square root; it goes inside: sqrt(Var + eps).",
     lambda z, gamma=1.0, eps=1e-4: _hinge(z.var(0).sqrt() + eps, gamma)),
    ("you used the variance where the standard deviation belongs: take sqrt(Var + eps).",
     lambda z, gamma=1.0, eps=1e-4: _hinge(z.var(0) + eps, gamma)),
    ("the hinge is missing: max(0, gamma - std) makes a dimension whose std is above gamma "
     "cost nothing, instead of earning a reward.",
     lambda z, gamma=1.0, eps=1e-4: (gamma - (z.var(0) + eps).sqrt()).mean()),
    ("you ignored the gamma argument (the target std): the hinge is max(0, gamma - std).",
     lambda z, gamma=1.0, eps=1e-4: _hinge((z.var(0) + eps).sqrt(), 1.0)),
    ("you returned one hinge per dimension; the term is their mean, a single number.",
     lambda z, gamma=1.0, eps=1e-4: torch.relu(gamma - (z.var(0) + eps).sqrt())),
]


@exercise(losses.variance_term, _VARIANCE_SLIPS, name="variance_term", hints=_VARIANCE_HINTS,
          answers=(losses.vicreg.variance_and_covariance, losses.vicreg_loss))
def check_variance_term(fn: Callable) -> bool:
    """Notebook 00: ``variance_term(z, gamma=1.0, eps=1e-4)`` on ``(B, D)``; value and
    gradient with respect to ``z``."""
    cases = _embedding_cases() + [
        Case("gamma=2.0", (torch.randn(32, 4, generator=torch.Generator().manual_seed(1)),),
             {"gamma": 2.0}),
    ]
    return compare(fn, losses.variance_term, cases, diagnoses=_VARIANCE_SLIPS,
                   grad=[(0, "z")], dims={0: "BD"}, swap=_ALONG_THE_BATCH,
                   factors={"D": "the hinge is averaged over the D dimensions, not summed"})


def _covariance(z: torch.Tensor, unbiased: bool = True, centre: bool = True) -> torch.Tensor:
    centred = z - z.mean(dim=0) if centre else z
    return centred.T @ centred / (len(z) - 1 if unbiased else len(z))


def _off_diagonal(cov: torch.Tensor) -> torch.Tensor:
    return cov - torch.diag(torch.diagonal(cov))


def _mean_square(cov: torch.Tensor, dim: int) -> torch.Tensor:
    return _off_diagonal(cov).pow(2).sum() / (dim * (dim - 1))


_COVARIANCE_HINTS = (
    "Dimensions that copy each other vary together over the batch. Measure how much each "
    "pair of different dimensions varies together, square it so that positive and negative "
    "correlations both count, and average over the pairs. A dimension with itself (its "
    "variance) is not a pair.",
    "C = (1/(B - 1)) * sum over b of (z_b - mean)(z_b - mean)^T, a D x D matrix, the mean "
    "taken over the batch. c(Z) = (1/(D(D - 1))) * sum over i != j of C_ij^2: the diagonal "
    "is left out, and there are D(D - 1) off-diagonal entries. Any correct way of getting C "
    "is accepted.",
    "centred = z minus its mean over the batch  # (B, D)\n"
    "cov = centred.T @ centred / (B - 1)  # (D, D)\n"
    "off = cov with its diagonal set to zero (without changing z)\n"
    "return off.pow(2).sum() / (D * (D - 1))",
)

_COVARIANCE_SLIPS = [
    ("you did not centre z: subtract its mean over the batch before multiplying.",
     lambda z: _mean_square(_covariance(z, centre=False), z.shape[1])),
    ("you kept the diagonal: C_jj is the variance of dimension j, not a covariance between "
     "two dimensions; leave it out of the sum.",
     lambda z: _covariance(z).pow(2).sum() / (z.shape[1] * (z.shape[1] - 1))),
    ("you averaged all D^2 squared entries, the diagonal (the variances) included; leave the "
     "diagonal out and divide by D(D - 1).", lambda z: _covariance(z).pow(2).mean()),
    ("you summed the covariances themselves; square them first (a positive and a negative "
     "correlation must not cancel).",
     lambda z: _off_diagonal(_covariance(z)).sum() / (z.shape[1] * (z.shape[1] - 1))),
    ("you took absolute values; the term squares the covariances.",
     lambda z: _off_diagonal(_covariance(z)).abs().sum() / (z.shape[1] * (z.shape[1] - 1))),
    ("torch.cov treats each row as a variable: z has one row per sample, so it needs the "
     "transpose of z.",
     lambda z: _mean_square(torch.cov(z), z.shape[1])),
]


@exercise(losses.covariance_term, _COVARIANCE_SLIPS, name="covariance_term",
          hints=_COVARIANCE_HINTS,
          answers=(losses.covariance_matrix, losses.vicreg.variance_and_covariance,
                   losses.vicreg_loss))
def check_covariance_term(fn: Callable) -> bool:
    """Notebook 00: ``covariance_term(z)`` on ``(B, D)``; value and gradient with respect to
    ``z``."""
    swap = (*_ALONG_THE_BATCH[:4], "Here z is (B, D), one row per sample: the covariance is "
            "between the D dimensions, D x D, each entry estimated over the batch (torch.cov, for "
            "one, treats each row as a variable)")
    return compare(fn, losses.covariance_term, _embedding_cases(seed=2),
                   diagnoses=_COVARIANCE_SLIPS, grad=[(0, "z")], dims={0: "BD"}, swap=swap,
                   factors={"D - 1": "the VICReg paper divides the sum by D; the course "
                                     "divides by D(D - 1), the number of off-diagonal "
                                     "entries, so that the term is their mean",
                            "D/(D - 1)": "there are D(D - 1) off-diagonal entries, not D^2",
                            "(B/(B - 1))²": "the sample covariance divides by B - 1, not B"})


# the weighted sum alone: what the learner writes, and what the training step of notebook 01
# calls (the learner's once it passes; this one, handed back, while it is not written)
_vicreg_total = losses.vicreg.vicreg


def _vicreg_slip(views=lambda term, a, b: (term(a) + term(b)) / 2,
                 invariance=losses.invariance_term, swap=False) -> Callable:
    """A VICReg loss with one mistake: another rule ``views(term, z_a, z_b)`` for applying
    the variance and covariance terms, another ``invariance``, or ``swap``ped weights."""
    def vicreg(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
        std_coeff, cov_coeff = (cov_coeff, std_coeff) if swap else (std_coeff, cov_coeff)
        return (inv_coeff * invariance(z_a, z_b)
                + std_coeff * views(losses.variance_term, z_a, z_b)
                + cov_coeff * views(losses.covariance_term, z_a, z_b))

    return vicreg


_VICREG_HINTS = (
    "The loss adds three things: how far apart the two views' embeddings are, how much "
    "spread each view lacks, and how correlated each view's dimensions are. The last two "
    "judge one batch of embeddings at a time, so apply them to each view on its own, then "
    "combine the two views.",
    "L = inv_coeff * s(z_a, z_b) + std_coeff * (v(z_a) + v(z_b)) / 2 "
    "+ cov_coeff * (c(z_a) + c(z_b)) / 2, with s the mean squared difference between the "
    "views, v the variance term and c the covariance term, all three imported at the top of "
    "the cell. Each takes (B, D) embeddings and gives a 0-d tensor; so does L.",
    "invariance = <the invariance term of the two views>\n"
    "variance = <the variance term of z_a and of z_b, averaged>\n"
    "covariance = <the same with the covariance term>\n"
    "return inv_coeff * invariance + std_coeff * variance + cov_coeff * covariance",
)

_ONE_VIEW = ("you regularised one view only; apply the variance and covariance terms to each "
             "view and average the two.")
_VICREG_SLIPS = [
    ("you added the two views' variance and covariance terms; average them (their sum over "
     "the two views, divided by 2).", _vicreg_slip(lambda term, a, b: term(a) + term(b))),
    (_ONE_VIEW, _vicreg_slip(lambda term, a, b: term(a))),
    (_ONE_VIEW, _vicreg_slip(lambda term, a, b: term(b))),
    ("you computed the variance and covariance on the two views stacked into one batch; "
     "compute each on one view, then average the two.",
     _vicreg_slip(lambda term, a, b: term(torch.cat([a, b])))),
    ("you swapped the weights: std_coeff multiplies the variance term, cov_coeff the "
     "covariance term.", _vicreg_slip(swap=True)),
    ("your invariance sums the squared difference over the D dimensions; the invariance "
     "term (the mean squared error) averages over them too.",
     _vicreg_slip(invariance=lambda a, b: (a - b).pow(2).sum(1).mean())),
    ("your invariance is an unsquared distance ||z_a - z_b||; it is the mean squared "
     "difference.", _vicreg_slip(invariance=lambda a, b: (a - b).norm(dim=1).mean())),
]


@exercise(_vicreg_total, _VICREG_SLIPS, name="vicreg", hints=_VICREG_HINTS,
          answers=(losses.vicreg_loss,))
def check_vicreg(fn: Callable) -> bool:
    """Notebook 01: ``vicreg(z_a, z_b, inv_coeff, std_coeff, cov_coeff)`` -> a 0-d tensor.

    Two views ``(B, D)``; the variance and covariance terms are computed on each
    view and averaged, as :func:`losses.vicreg_loss` does. Value and gradients with
    respect to both views.
    """
    g = torch.Generator().manual_seed(5)
    z = torch.randn(32, 8, generator=g)
    mixed = torch.randn(48, 1, generator=g) * torch.tensor([[1.0, -0.5, 2.0, 0.1]])
    cases = [
        Case("two random views (32, 8), coefficients 1, 1, 80",
             (z, z + 0.3 * torch.randn(32, 8, generator=g), 1.0, 1.0, 80.0)),
        Case("views with different spreads (std 0.5 and 3), coefficients 25, 25, 1",
             (0.5 * torch.randn(64, 6, generator=g), 3 * torch.randn(64, 6, generator=g),
              25.0, 25.0, 1.0)),
        Case("only the variance weight set (0, 1, 0), views of std 0.2 and 0.8",
             (0.2 * torch.randn(16, 5, generator=g), 0.8 * torch.randn(16, 5, generator=g),
              0.0, 1.0, 0.0)),
        Case("only the covariance weight set (0, 0, 1), one view correlated",
             (mixed + 0.1 * torch.randn(48, 4, generator=g), torch.randn(48, 4, generator=g),
              0.0, 0.0, 1.0)),
        Case("two identical collapsed views (every row the same), coefficients 2, 3, 4",
             (torch.ones(8, 3), torch.ones(8, 3), 2.0, 3.0, 4.0)),
        Case("two float64 views (16, 4), coefficients 1, 2, 3",
             (torch.randn(16, 4, generator=g, dtype=torch.float64),
              torch.randn(16, 4, generator=g, dtype=torch.float64), 1.0, 2.0, 3.0)),
    ]
    return compare(fn, _vicreg_total, cases, diagnoses=_VICREG_SLIPS,
                   grad=[(0, "the first view z_a"), (1, "the second view z_b")],
                   dims={0: "BD"})


def _vicreg_paper_to_ebjepa(inv: float, std: float, cov: float, dim: int) -> tuple:
    """Reference: VICReg-paper coefficients -> EB-JEPA coefficients (invariance weight 1).

    The covariance sum is divided by ``D`` in one and by ``D (D - 1)`` in the
    other, so its weight grows by ``D - 1``; dividing every weight by the
    invariance weight leaves the loss's shape unchanged (only its scale).
    """
    return 1.0, std / inv, cov * (dim - 1) / inv


_CONVERSION_HINTS = (
    "The two papers scale the covariance term differently, so the same loss needs different "
    "weights. Find how many times smaller EB-JEPA's covariance term is than the VICReg "
    "paper's, make its weight that many times larger, then rescale all three weights so "
    "that the invariance weight becomes 1 (only their ratios shape the loss).",
    "c_VICReg = (D - 1) * c_EB-JEPA, so nu * c_VICReg = nu * (D - 1) * c_EB-JEPA. Then divide "
    "every weight by the invariance weight lambda. Return three Python numbers: the "
    "invariance, variance and covariance weights.",
    "return 1.0, <std divided by inv>, <cov times (dim - 1), divided by inv>",
)

_CONVERSION_SLIPS = [
    ("you forgot the factor (D - 1): the paper divides the covariance sum by D, EB-JEPA by "
     "D(D - 1), a term D - 1 times smaller, so its weight must be D - 1 times larger.",
     lambda inv, std, cov, dim: (1.0, std / inv, cov / inv)),
    ("you multiplied the covariance weight by D; the ratio of the two divisors is "
     "D(D - 1) / D = D - 1.", lambda inv, std, cov, dim: (1.0, std / inv, cov * dim / inv)),
    ("you divided the covariance weight by (D - 1); EB-JEPA's term is D - 1 times smaller "
     "than the paper's, so its weight must grow by D - 1.",
     lambda inv, std, cov, dim: (1.0, std / inv, cov / (dim - 1) / inv)),
    ("you divided the covariance weight by inv but not the variance weight: divide all three.",
     lambda inv, std, cov, dim: (1.0, std, cov * (dim - 1) / inv)),
    ("you did not divide by the invariance weight: divide all three weights by inv, so that "
     "the invariance weight is 1.", lambda inv, std, cov, dim: (inv, std, cov * (dim - 1))),
    ("you divided the weights by the variance weight std; EB-JEPA's invariance weight is 1, "
     "so divide all three by inv.",
     lambda inv, std, cov, dim: (inv / std, 1.0, cov * (dim - 1) / std)),
]


@exercise(_vicreg_paper_to_ebjepa, _CONVERSION_SLIPS, name="vicreg_paper_to_ebjepa",
          hints=_CONVERSION_HINTS)
def check_vicreg_paper_to_ebjepa(fn: Callable) -> bool:
    """Notebook 01: ``vicreg_paper_to_ebjepa(inv, std, cov, dim)`` -> three floats."""
    name = getattr(fn, "__name__", "your function")
    cases = [(25.0, 25.0, 1.0, 2048), (25.0, 25.0, 1.0, 8192), (10.0, 25.0, 1.0, 1024),
             (5.0, 5.0, 1.0, 128), (2.0, 1.0, 0.5, 3)]
    for args in cases:
        case = Case("inv={:g}, std={:g}, cov={:g}, dim={}".format(*args), args)
        got, where = _run(fn, name, case)[0], case.description
        if isinstance(got, torch.Tensor) or not hasattr(got, "__len__") or len(got) != 3:
            raise ExerciseError(f"{name} returned {_describe(got)} on {where}; expected a tuple "
                                "of three numbers (invariance, variance, covariance weights).")
        try:
            values = [float(v) for v in got]
        except (TypeError, ValueError):
            raise ExerciseError(f"{name} returned {got!r} on {where}; expected numbers.") from None
        expected = _vicreg_paper_to_ebjepa(*args)
        for k, (label, value, answer) in enumerate(zip(("invariance", "variance", "covariance"),
                                                       values, expected)):
            if abs(value - answer) > 1e-6 * max(1.0, abs(answer)):
                one = [(words, lambda *a, v=v, k=k: v(*a)[k])  # the slips of this weight alone
                       for words, v in _CONVERSION_SLIPS]
                raise ExerciseError(
                    f"{name} gave {label} weight {value:.6g} on {where}, but the answer is "
                    f"{answer:.6g} (all three: {tuple(round(a, 6) for a in expected)})."
                    + diagnose(value, one, case, atol=1e-6))
    print(f"Correct: {name} matches the reference on {len(cases)} test inputs.")
    return True
