"""The browser view served by the API: static pages that read the same REST routes as the SDK."""
