"""One module per group of ``rlu`` subcommands; each defines ``register(subparsers)``."""
