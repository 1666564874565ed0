"""The data types: :class:`~clsas.Dataset`, :class:`~clsas.Profiles`, :class:`~clsas.Image` (immutable once
built, with their files and pictures), what a grid needs from the data (the range gate, the checks
made before any work) and the stage-named :class:`~clsas.Progress`."""
