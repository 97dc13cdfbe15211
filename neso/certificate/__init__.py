"""Small-gain stability certificate of Neural-ESO (paper Section IV, Lemma 1 and Theorem 1).

Pure numpy/scipy, no I/O; the ``lmi`` method also imports cvxpy and Clarabel (lazily, inside it).

Error states (per axis; SI units, so the stacked vectors have mixed units):

* tracking ``e_state = [e, ė]``              (m, m/s),            dynamics ``ė_s = A_e e_s + B_e f̃``
* observer ``ẽ_obs  = [x̃1, x̃2, f̃]``         (m, m/s, m/s²),      dynamics ``ẽ̇ = A_obs ẽ + B_obs Δḟ``
* ``E = [e_state, ẽ_obs]``; ``‖E‖`` is the Euclidean norm of that mixed-unit vector.

Lemma 1: ``‖Δḟ‖ ≤ γ_e ‖e_state‖ + γ_ẽ ‖ẽ_obs‖ + C_f`` with ``γ_e = L_N λ_c``, ``γ_ẽ = L_N``,
``C_f = L_1 + L_N C_z``, ``C_z = L_u + ‖q̇*‖max + ‖q̈*‖max``.

**n axes.** With identical diagonal gains ``k_p I_n, k_d I_n, β_i I_n`` every matrix is a Kronecker product
``A ⊗ I_n``; eigenvalues, Lyapunov solutions' spectra and induced 2-norms are those of the 1-axis matrices, so the
n-axis certificate equals the 1-axis one (``L_N`` being the Lipschitz constant of the whole vector map ``f_N``).
The optimisers work per axis; :func:`verify_certificate` rebuilds the n-axis matrices and checks the claim.

**λ_c and a gap in the paper's Lemma 1.** ``ż`` contains ``ẋ1 = q̇* − ė``, whose ``‖ė‖`` the printed proof drops:
``‖ż‖ ≤ C_z + ‖ė‖ + ‖k_p e‖ + ‖k_d ė‖ + ‖f̃‖``. ``lambda_c_rule="corrected"`` (default) uses
``λ_c = sqrt(k_p² + (k_d+1)²)`` which covers that term (Cauchy–Schwarz); ``"paper"`` uses the printed
``λ_c = sqrt(k_p² + k_d²)`` to reproduce the paper literally.

**Units of L_N.** Physical Lipschitz constant of ``f_N`` in (m/s²) per unit of the mixed-SI input ``z``.
A network's normalised bound converts as ``L_phys = L_norm · σ_y / min_i σ_{z,i}``.

Three methods (all under the same Lemma-1 bound and λ_c rule):

* ``literal`` — the paper's proof as written: ``Q_e = I``, ``Q_obs = I``, unit weights, separate Young splits with
  free ``δ_e, δ_o, δ_c``. Optimising ``δ_e, δ_o`` with ``δ_c → 0`` the supremum margin is exactly
  ``λ_min(M)`` of the 2×2 matrix ``M = [[λ_e, −(‖P_eB_e‖ + c_pb γ_e)], [·, λ_o − 2 c_pb γ_ẽ]]`` (the balanced split
  ``δ_e = (λ_e−m)p/(a+p)``, ``δ_o = (μ−m)a/(a+p)`` attains it), so the verdict is
  ``λ_e (λ_o − 2 c_pb L_N) > (‖P_eB_e‖ + c_pb λ_c L_N)²`` — closed form and monotone in ``L_N``
  (left side decreasing, right side increasing). ``δ_c`` only trades margin against the bound; the reported
  ``δ_e, δ_o, δ_c`` minimise the ultimate bound ``sqrt(C_o/α)`` among all valid certificates
  (``δ_c`` in closed form, ``δ_e, δ_o`` by Nelder–Mead in log space from the max-margin point).
* ``tight`` — same Lemma-1 bound, more freedom: diagonal scalings ``η = T_e e_state``, ``ξ = T_o ẽ_obs`` (bandwidth
  scaling), diagonal ``Q̄_e, Q̄_o`` in the scaled coordinates, weight ``V = s·ηᵀP̄_eη + ξᵀP̄_oξ``, and the 2×2
  positive-definiteness condition in ``(‖η‖, ‖ξ‖)`` instead of Young splits. Lemma 1 stays in unscaled norms and is
  converted with ``‖e_state‖ ≤ κ_e‖η‖``, ``‖ẽ_obs‖ ≤ κ_o‖ξ‖`` (``κ = 1/min diag T``) and ``|f̃| ≤ ‖ξ‖/t_o3``. The
  certified ``L_N`` of one parameter set is the root of a quadratic; it is maximised by multi-start Nelder–Mead.
  Every reported certificate is re-verified from its parameters by :func:`verify_certificate`.
* ``lmi`` — a quadratic ``V = EᵀPE`` over the composite error with the paper's closed loop ``Ė = AE + BΔḟ``,
  ``A = [[A_e, B_e S], [0, A_obs]]`` (``S`` picks ``f̃``), ``B = [0; B_obs]``; ``P`` block-diagonal
  (``structure="block"``: the paper's ``V_e + V_obs`` with free ``P_e, P_obs``) or full (``"full"``, cross terms
  ``e_sᵀP_eoẽ`` allowed; the default, see below). Lemma 1 enters by the S-procedure. Split the input: every
  ``Δḟ`` with ``‖Δḟ‖ ≤ γ_e‖e_s‖ + γ_ẽ‖ẽ‖ + C_f`` is ``a + b + w`` with ``‖a‖ ≤ γ_e‖e_s‖``, ``‖b‖ ≤ γ_ẽ‖ẽ‖``,
  ``‖w‖ ≤ C_f`` (give each term its share of ``Δḟ``). If, with multipliers ``τ_e, τ_ẽ ≥ 0``, ``α > 0``, ``μ``,

      M = [[AᵀP + PA + αP + τ_eγ_e²Π_e + τ_ẽγ_ẽ²Π_o,  PB,   PB,   PB ],
           [BᵀP,                                   −τ_e,  0,    0  ],
           [BᵀP,                                   0,    −τ_ẽ,  0  ],
           [BᵀP,                                   0,     0,   −μ  ]] ⪯ 0,   P ≻ 0

  (``Π_e``, ``Π_o`` the projections on ``e_s``, ``ẽ``), then multiplying by ``[E; a; b; w]`` on both sides gives
  ``V̇ + αV ≤ μ‖w‖² − τ_e(γ_e²‖e_s‖² − ‖a‖²) − τ_ẽ(γ_ẽ²‖ẽ‖² − ‖b‖²) ≤ μC_f²``: ``V`` ends in
  ``{V ≤ μC_f²/α}`` and ``‖E‖`` in ``C_f·sqrt(μ/(α λ_min P))`` (that sublevel set is the eventual set itself, so
  ``ultimate_bound = ultimate_bound_sublevel``; ``α`` is the decay rate of ``V``, 1/s, reported as ``alpha``).
  *Two multipliers, not Young's ε.* The single-multiplier form with ``(γ_e‖e‖ + γ_ẽ‖ẽ‖)² ≤ (1+ε)γ_e²‖e‖² +
  (1+1/ε)γ_ẽ²‖ẽ‖²`` is valid for every ``ε > 0``. Eliminating the input blocks (Schur), the two-multiplier
  condition is ``AᵀP+PA+τ_eγ_e²Π_e+τ_ẽγ_ẽ²Π_o + (1/τ_e+1/τ_ẽ)PBBᵀP ≺ 0`` and the ε one is
  ``AᵀP+PA+τ((1+ε)γ_e²Π_e+(1+1/ε)γ_ẽ²Π_o) + PBBᵀP/τ ≺ 0``; ``τ_e = τ(1+ε)``, ``τ_ẽ = τ(1+1/ε)`` give
  ``1/τ_e + 1/τ_ẽ = 1/τ``, so the two coincide: the two-multiplier LMI is the ε-family swept over every ``ε``
  at once, and jointly convex. (Sufficient, not necessary: the S-procedure with two constraints can be lossy.)
  *Verdict.* Strict feasibility of the 3-block LMI (``α = 0``, no ``w``), which is equivalent to feasibility of
  ``M ≺ 0`` for some ``α > 0``, ``μ``. ``L_N`` enters only through ``τ_eγ_e²Π_e + τ_ẽγ_ẽ²Π_o ⪰ 0``, increasing
  in ``L_N``, so a certificate at ``L`` is one at every smaller ``L`` (monotone): the largest ``L_N`` is found by
  bisection on "the SDP is strictly feasible and its ``P`` verifies" (``max t`` with ``M ⪯ −tI``, ``P ⪰ tI``,
  ``tr P + τ_e + τ_ẽ = 1``, in bandwidth-scaled coordinates for the solver only). The bound at a given ``L_N``
  comes from a second SDP (min ``μ`` with ``P ⪰ I`` over a search on ``α``).
  *It contains tight.* Tight's ``V`` (block-diagonal) with ``τ_e = a·c_pb/((p+q)γ_eκ_e)``, ``τ_ẽ = c_pb/(γ_ẽκ_o)``
  (``a, p, q`` the entries of its 2×2 ``M``) satisfies the block LMI whenever tight holds, so
  block ≥ tight; full ≥ block trivially. *Never trust the solver.* The solver only proposes ``P, τ``;
  :func:`verify_lmi` rebuilds ``M`` for ``n`` axes in numpy and demands ``λ_max(DMD) ≤ −10⁻⁹`` after the
  rounding error of assembling it (``D`` the Jacobi scaling, :func:`negative_margin`) and ``P ≻ 0`` likewise;
  a proposal that fails is not a certificate (the bisection treats it as infeasible; a verdict is withdrawn).
  *Which P.* Both are quadratic Lyapunov functions of the same ``E`` under the same Lemma 1 with the same
  conclusion (UUB of ``E``); full contains block, certifies 0–25 % more ``L_N`` on the gain grid of
  ``neso/README.md`` (4 % at the flown gains) at the same cost, and is kept as ``method="lmi"``. Block stays
  selectable (``certify_lmi(..., structure="block")``) as the paper's ``V_e + V_obs`` read literally.

Bounds reported (both in the mixed units of ``E``):

* ``ultimate_bound`` — the paper's radius: ``V̇ < 0`` whenever ``‖E‖`` exceeds it.
* ``ultimate_bound_sublevel`` — what trajectories eventually satisfy: the smallest sublevel set of ``V`` that
  contains that ball, ``‖E‖ ≤ r·sqrt(λ_max(P̄)/λ_min(P))`` (``P̄`` scaled, ``P`` unscaled Lyapunov matrix).
  Compare simulated ``‖E(t)‖`` against this one.
"""
from neso.certificate.best import best_certificate, certify, max_certified_lipschitz, max_certified_lipschitz_best
from neso.certificate.flight import (POLICY, CertificatePolicy, FlightCertificate, LoopPlant, NetworkSlopes,
                                     ReferenceBounds, exogenous_rates, flight_budget, flight_certificate)
from neso.certificate.roles import (RoleCertificate, RoleInputs, certify_roles, max_certified_state_lipschitz,
                                    max_certified_state_lipschitz_verified, verify_roles)
from neso.certificate.core import (METHODS, CertificateInputs, CertificateResult, Method, composite_matrices,
                                   lyapunov_residual, negative_margin, observer_gains, observer_matrices,
                                   solve_lyapunov, tracking_matrices)
from neso.certificate.lmi import (LMI_STRUCTURE, LMI_STRUCTURES, _lmi_frontier, _lmi_programs, certify_lmi,  # noqa: F401
                                  lmi_matrix, verify_lmi)
from neso.certificate.literal import certify_literal
from neso.certificate.tight import TightParams, certify_tight
from neso.certificate.verify import verify_certificate

__all__ = ["POLICY", "CertificatePolicy", "LoopPlant", "NetworkSlopes", "ReferenceBounds", "exogenous_rates",
           "RoleCertificate", "RoleInputs", "certify_roles", "flight_budget", "max_certified_state_lipschitz",
           "max_certified_state_lipschitz_verified", "verify_roles", "METHODS", "LMI_STRUCTURE", "LMI_STRUCTURES", "CertificateInputs", "CertificateResult", "FlightCertificate",
           "Method", "TightParams", "best_certificate", "certify", "certify_lmi", "certify_literal", "certify_tight",
           "composite_matrices", "flight_certificate", "lmi_matrix", "lyapunov_residual", "max_certified_lipschitz",
           "max_certified_lipschitz_best", "negative_margin", "observer_gains", "observer_matrices", "solve_lyapunov",
           "tracking_matrices", "verify_certificate", "verify_lmi"]
