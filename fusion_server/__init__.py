"""fusion_server package."""
