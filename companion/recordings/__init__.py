"""Recordings: the columnar form, the .tlog reader and writer, the importers, ``load_recording``
(``load``) and the signal path (``signals``)."""
