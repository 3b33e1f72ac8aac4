"""The one exception the data layer raises for bad input."""


class DataError(ValueError):
    """Input data is missing, malformed or unsupported; the message names the file and the problem."""
