"""What a person looks at: coloured clouds, static figures (matplotlib), obstacle meshes and the self-contained HTML report (plotly)."""
