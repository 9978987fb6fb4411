"""Agents. Each algorithm is one module here, its hyperparameters declared in ``schemas.py``
(the menu ``conf/algo/<name>.yaml`` is written from there: ``make menus``)."""
