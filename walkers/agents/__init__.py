"""Agents. Each algorithm is one module here plus one ``conf/algo/*.yaml``."""
