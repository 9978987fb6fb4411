"""Agents, in three kinds of module. Here: each algorithm, one module owning its update (the
ones ``declarations.schemas.SCHEMAS`` declares), the Agent interface (``base``) and the factory.
``common/``: the parts the algorithms share. ``declarations/``: each algorithm's hyperparameters,
declared once in ``schemas.py`` (the menu ``conf/algo/<name>.yaml`` is written from there:
``make menus``). ``sb3/``: the Stable-Baselines3 twins behind the same interface."""
