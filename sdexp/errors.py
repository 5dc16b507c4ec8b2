"""Errors that are the user's to fix: printed as one clear message, never as a traceback."""


class UserError(Exception):
    """Bad input (config value, file, column): the message names it and the allowed range."""
