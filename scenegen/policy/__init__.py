"""Learning and judging what to do: expert labels (``labels``), success tables, failure labels, the
baseline primitive chooser (``network``, ``train``, ``evaluate``) and the panels. Seeing is
``scenegen.perception``, acting ``scenegen.manipulation``."""
