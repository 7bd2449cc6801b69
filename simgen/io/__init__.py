"""Input/output: USD export of mesh sequences (``simgen.io.usd``) and offscreen rendering
(``simgen.io.render``). usd-core and pyvista are imported inside the functions that use them."""

from simgen.io.usd import MeshTrack, read_usd_info, read_usd_meshes, validate_usd, write_usd

__all__ = ["MeshTrack", "write_usd", "read_usd_meshes", "read_usd_info", "validate_usd"]
