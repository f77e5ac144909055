"""The REST service (FastAPI): thin routers over ``jobs`` (queue, records, storage) and
``eva_engine`` (rendering). ``create_app(settings)`` builds one app; ``eva serve`` runs it.

    from service.app import create_app
    from service.settings import ServiceSettings
    app = create_app(ServiceSettings.from_env())

This file imports nothing, so that ``eva`` (``service.cli``) and the container's health check
start without FastAPI and torch.
"""
