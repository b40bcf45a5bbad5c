"""bodyspace: statistical human body models on a laptop CPU.

Layers (each imports only from those before it): ``mesh`` → ``data`` (assets, template,
phenotype, rig, population, database) → ``cli``/``report``.
"""

from bodyspace.errors import BodyspaceError

__version__ = "0.1.0"
__all__ = ["BodyspaceError", "__version__"]
