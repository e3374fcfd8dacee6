"""Studies of integrators on any system and scene: work–precision (:mod:`.workprecision`),
stability maps (:mod:`.stability`), ``select`` (:mod:`.select`), network-size sweeps
(:mod:`.sweep`), the demo's rollouts (:mod:`.demo`) and their figures (:mod:`.figures`).

Every study is written against a small interface of the system: ``dim``, ``hamiltonian(mu)``,
``casimirs(mu)`` (None when unknown: the drift is then NaN, never 0), ``component_names`` and
``name``; a system without the last two gets μ₁…μₙ and its class name.
"""
