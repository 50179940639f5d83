"""The causes the diagnosis can name (the CLI contract's list) and what each one means."""

from __future__ import annotations

CAUSES = ("none", "output_feedback", "parallel_path", "output_nonlinearity", "backlash", "time_varying",
          "unmodeled_dynamics", "periodic_disturbance", "input_dynamics")

MEANING = {
    "none": "nothing a Hammerstein model cannot represent: the baseline is adequate",
    "output_feedback": "a static nonlinearity of the output fed back into the linear block",
    "parallel_path": "a linear path in parallel with the Hammerstein branch (feedforward system)",
    "output_nonlinearity": "a static nonlinearity after the linear block (sensor saturation, dead zone, ...)",
    "backlash": "a nonlinearity with memory at the input (play, backlash, hysteresis)",
    "time_varying": "the linear block or the gain changes during the record (drift or step change)",
    "unmodeled_dynamics": "the linear block has more dynamics than the nominal order",
    "periodic_disturbance": "an additive periodic signal not caused by the input",
    "input_dynamics": "a linear block before the static map (Wiener-Hammerstein, L-N-L: a filter, a sensor or an "
                      "amplifier stage ahead of the nonlinearity)",
}

EXTENSION = {
    "output_feedback": "Hammerstein / non-linear feedback y = G[f(u) - h(y)] (PLLS, paper 001), or two storages in "
                       "series, each with a level-dependent outflow",
    "parallel_path": "feedforward y = G1[F(u)] + G2[u] (Billings-Fakhouri, paper 003)",
    "output_nonlinearity": "Hammerstein-Wiener y = N(G[F(u)])",
    "backlash": "play operator of estimated width before the static map, y = G[F(P_w(u))]",
    "time_varying": "sliding-window re-identification of the linear block",
    "unmodeled_dynamics": "Hammerstein model of higher order, chosen on the estimation data (BIC)",
    "periodic_disturbance": "Hammerstein model plus sinusoids at the residual-spectrum lines",
    "input_dynamics": "Wiener-Hammerstein y = G2[f(G1[u])] from the split of the best linear approximation",
}
