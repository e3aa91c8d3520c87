"""Subcommands of ``passt-mav`` (one module each; standard-library imports only at top)."""
