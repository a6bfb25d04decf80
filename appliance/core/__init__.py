"""The measurement's mathematics: layouts, meshes, forward models, reconstruction and pressure maps.

A package (not a namespace) so that import checks see its modules; it imports nothing itself.
"""
