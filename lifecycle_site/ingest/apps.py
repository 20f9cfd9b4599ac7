from django.apps import AppConfig


class IngestConfig(AppConfig):
    """What the gateways report, stored: the ingest process (``manage.py ingest``) and the facts it
    applies (audit records, states, logs, absences, outages), and the live updates of the pages."""

    name = "lifecycle_site.ingest"
    verbose_name = "Ingest"
