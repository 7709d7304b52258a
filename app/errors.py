"""The error a command reports to its user: one line, exit status 2."""


class UserError(Exception):
    """An error the user can act on: printed as one line, exit status 2."""
