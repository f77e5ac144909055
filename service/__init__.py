"""The REST service (FastAPI): thin routers over ``jobs`` (queue, records, storage) and
``eva_engine`` (rendering). ``create_app(settings)`` builds one app; ``eva serve`` runs it.

    from service import ServiceSettings, create_app
    app = create_app(ServiceSettings.from_env())
"""

from service.app import create_app
from service.settings import ServiceSettings

__all__ = ["ServiceSettings", "create_app"]
