"""Small helpers every layer may use: tensor utilities and parameter checks.

Nothing here knows about meshes or the method; it imports only torch and numpy.
"""
