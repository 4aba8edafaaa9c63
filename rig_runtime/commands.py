"""Subcommands beyond ``tune`` (registered on import by ``cli.build_parser``)."""
