"""Errors that every edge of the product (CLI, API, jobs) maps the same way, raised from every layer
(hence the root)."""


class InputError(ValueError):
    """The input cannot be used: a bad file, column, value, or data too degenerate to fit.

    The CLI exits with status 2 on it and the API answers 422; the message always says
    what is wrong and where (file, row, column, field), in one line.
    """


class DegenerateDataError(InputError):
    """The data are valid but do not determine what was asked of them."""


class FitError(RuntimeError):
    """A fit ran but did not converge to a usable model."""
