"""Importers into the canonical scene directory (:mod:`trace3d.scene`): ``synthetic`` (procedural
ray-cast rooms), ``replica``, ``llff`` (NVOS), plus helpers that read a canonical scene's extras."""
