"""thci: history-based reinforcement learning with causal memory (T-HCI).

Importing the package registers the built-in gymnasium environments (``thci/PaperMaze-L1-v0``
... ``thci/PaperMaze-L4-v0``).
"""

from thci import envs as _envs  # noqa: F401  (registers the environments)

__version__ = "0.1.0"
