"""The three systems: ``toktalk``, ``freetalk`` and ``timar``."""
