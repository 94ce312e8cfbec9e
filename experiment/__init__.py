"""trustlab's experiment core: the task, schedules, policies, the trust IOHMM,
the belief-MDP policy, simulated participants and statistics.

Pure Python + numpy/scipy/pydantic: nothing here imports a web framework or a
database, so every piece runs and is tested without a server.
"""
