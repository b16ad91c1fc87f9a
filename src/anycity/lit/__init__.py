"""Lightning wrappers: Stage I :class:`ScaffoldModule`, Stage II :class:`RefinementModule`, the data module.

Importing this package imports Lightning; ``anycity.models``/``render``/``data`` never do.
"""

from anycity.lit.base import AnyCityModule
from anycity.lit.refinement import RefinementModule
from anycity.lit.scaffold import ScaffoldModule

__all__ = ["AnyCityModule", "ScaffoldModule", "RefinementModule"]
