"""The three systems: ``toktalk``, ``freetalk`` and ``timar``; and ``dualtalk``, the non-causal baseline of
TIMAR's Table 1."""
