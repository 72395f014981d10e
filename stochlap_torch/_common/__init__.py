"""Small helpers every layer may use; nothing here knows about meshes or the method."""
