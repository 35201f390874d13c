"""The wizard's calibration session as values: the typed session file (``model``) and its steps,
functions that take the session and what they need and return a new value, never asking or
printing (``plan``, ``record``, ``fit``, ``save``). ``calibration.wizard`` is the terminal that
asks, prints and drives them."""
