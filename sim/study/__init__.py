"""sim.study: the Monte Carlo study of Diab et al., "Artificial Potential Field-Based Path Planning for
Cluttered Environments", IEEE Aerospace 2023 (DOI 10.1109/AERO55745.2023.10115857), Section "Simulations".

Modules:
- ``config``   the frozen study configuration and its two presets (``reference``: the authors' code,
               ``paper``: the paper's text), and obstacle densities
- ``worlds``   random point-obstacle fields, padded to ``(A, N_max, D)`` with masks
- ``engine``   the lockstep batched engine: thousands of trials advance together as one array program,
               split into fixed seeded chunks that any ``concurrent.futures.Executor`` can run
- ``metrics``  R_s with its Wilson 95 % interval, M_s, S, T_a and outcome counts
- ``paper``    the paper's Table values, for side-by-side printing
- ``report``   markdown table, JSON and CSV output
- ``plots``    the study's figures (matplotlib, Agg)
- ``worldstudy`` the study over world files (``--world``): surface samples for the planners, true geometry for
               collisions and clearance
- ``optimal``  the full-knowledge grid optimum (Dijkstra + any-angle refinement); ``fieldoptimum`` runs it on
               the random fields (``--optimum``)
- ``cli``      ``apf-sim study`` (also ``python -m sim.study``)

This package file deliberately imports nothing heavy: worker processes import ``sim.study._worker`` first to
limit BLAS threads before numpy loads.
"""
