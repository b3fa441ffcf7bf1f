"""tmrl: distributed real-time reinforcement learning.

Importing this package has no side effects: it reads no file, writes no folder and leaves
logging alone. Configuration is read when a command or an object needs it.
"""

__version__ = "0.1.0"
