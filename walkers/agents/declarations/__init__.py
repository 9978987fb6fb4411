"""Each algorithm's hyperparameters, declared once (``schemas``) with the machinery that checks
them (``hyperparameters``) and writes the menus ``conf/algo/<name>.yaml`` (``menus``). Every list
of algorithms derives from ``schemas.SCHEMAS``."""
