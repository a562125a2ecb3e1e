"""The ``softsim`` command line: one module per subcommand, ``cli.main`` the entry point.
"""
