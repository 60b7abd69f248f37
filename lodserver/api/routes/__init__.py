"""One router per resource: meshes (catalogue), lods (levels and packets), health."""
