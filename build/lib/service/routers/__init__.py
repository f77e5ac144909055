"""Thin routers: validate (schemas, deps), call ``jobs`` / ``service.rendering``, answer."""
