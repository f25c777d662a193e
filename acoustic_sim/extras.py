"""Optional extras (pip install ".[ros]", ".[chirp]", ".[crossengine]"): the error when one is missing."""


class MissingExtra(ImportError):
    """An optional extra is not installed; the message names what to install. The command line
    shows it as one `error:` line, while any other ImportError (a real bug) keeps its trace."""
