"""The physics floor: sound in air, waveforms, geometry (apertures, grids, scenes), beams, specular
surfaces and the errors of hand-held scans. Imports nothing above it but :mod:`clsas.validate`."""
