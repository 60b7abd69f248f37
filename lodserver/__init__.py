"""lodserver: decimate once, serve every level of detail."""
