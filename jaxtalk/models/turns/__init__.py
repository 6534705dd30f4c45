"""What the turn models share: TIMAR and its DualTalk baseline read the same conversation streams
(both sides' speech and motion, cut into 1-s turns), train on the same turn windows with the same
settings, and are scored by the same protocol. TIMAR's Table 1 retrains DualTalk "under the same
training configuration as TIMAR"; this family package holds that common ground so that neither model
imports the other.

* :mod:`~jaxtalk.models.turns.streams`: the streams' checks and their split into turns.
* :mod:`~jaxtalk.models.turns.windows`: a prepared dataset's conversation sides and turn windows.
* :mod:`~jaxtalk.models.turns.training`: the shared training, validation and evaluation of a side.
"""
