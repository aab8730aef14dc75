"""Control through contacts: optimise initial states through the simulator (the paper's control tasks).

:mod:`~diffcontact.control.optimise` (Levenberg–Marquardt with a batched line search, Adam),
:mod:`~diffcontact.control.billiards` and :mod:`~diffcontact.control.throw` (the two problems),
:mod:`~diffcontact.control.run` (the commands) and :mod:`~diffcontact.control.outputs` (figures, GIFs, JSON).
"""
