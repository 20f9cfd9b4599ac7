"""Delivery log rows written before URLs with credentials were refused could hold a URL's
user name and password ("could not reach http://user:password@host/..."): replace them by ***."""
import re

from django.db import migrations

CREDENTIALS = re.compile(r"(https?://)[^/\s]*@", re.IGNORECASE)


def redact_errors(apps, schema_editor) -> None:
    Delivery = apps.get_model("alerts", "Delivery")
    for row in Delivery.objects.filter(error__contains="@").only("id", "error").iterator():
        redacted = CREDENTIALS.sub(r"\1***@", row.error)
        if redacted != row.error:
            Delivery.objects.filter(pk=row.pk).update(error=redacted)


class Migration(migrations.Migration):
    dependencies = [("alerts", "0001_alert_rules")]
    operations = [migrations.RunPython(redact_errors, migrations.RunPython.noop)]
