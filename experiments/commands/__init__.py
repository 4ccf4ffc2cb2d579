"""Sub-commands of the ``iarcs`` command line; each module defines ``register(subparsers)``."""
