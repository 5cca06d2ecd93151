"""Non-metric visual servoing control: the DVS and decoupled DVS errors, their interaction matrices at the
equilibrium, the stability conditions of Theorems 3.1/3.2 and the saturated control laws (12), (25).

Modules: `errors` (control errors (7)–(16)), `interaction` (interaction matrices (19), (20) and the closed-loop
spectrum of Theorem 3.2, analysis only), `stability` (configuration checks (17), (18), (26)–(28), (34), (35)),
`law` (`ControlConfig`, `ControlLaw`).
"""
