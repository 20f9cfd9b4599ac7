"""Gateways: every robot belongs to one. Existing robots go to the gateway "local" (the one on
the site's machine, as before); the old heartbeat table goes (heartbeats now live in Redis)."""

import django.core.validators
import django.db.models.deletion
import lifecycle_site.fleet.models
import re
from django.db import migrations, models

LOCAL = "local"


def robots_to_local(apps, schema_editor) -> None:
    Gateway = apps.get_model("fleet", "Gateway")
    Robot = apps.get_model("fleet", "Robot")
    local, _ = Gateway.objects.get_or_create(
        name=LOCAL, defaults={"description": "The gateway on the site's own machine."}
    )
    Robot.objects.filter(gateway__isnull=True).update(gateway=local)


class Migration(migrations.Migration):

    dependencies = [
        ('fleet', '0003_order_help'),
    ]

    operations = [
        migrations.CreateModel(
            name='Gateway',
            fields=[
                ('id', models.BigAutoField(auto_created=True, primary_key=True, serialize=False, verbose_name='ID')),
                ('name', models.CharField(max_length=63, unique=True, validators=[django.core.validators.RegexValidator(re.compile('^[a-z0-9][a-z0-9_-]{0,62}$'), "Use lower-case letters, digits, '-' and '_', starting with a letter or digit (for example cell-a).")])),
                ('description', models.TextField(blank=True)),
                ('created', models.DateTimeField(auto_now_add=True)),
                ('redis_password_sha256', models.CharField(blank=True, editable=False, max_length=64)),
                ('last_beat', models.DateTimeField(blank=True, null=True)),
                ('started', models.DateTimeField(blank=True, null=True)),
                ('stopped', models.BooleanField(default=False, help_text='Its last heartbeat said it stopped cleanly.')),
                ('instance', models.CharField(blank=True, help_text='Id of its running process.', max_length=32)),
                ('version', models.CharField(blank=True, max_length=64)),
                ('host', models.CharField(blank=True, max_length=255)),
                ('pid', models.PositiveIntegerField(blank=True, null=True)),
                ('domains', models.JSONField(blank=True, default=list, verbose_name='ROS domains')),
                ('dds', models.JSONField(blank=True, default=dict, verbose_name='DDS discovery settings')),
                ('node_count', models.PositiveIntegerField(default=0, verbose_name='nodes')),
                ('outbox', models.JSONField(blank=True, default=dict, help_text='What it held or dropped while Redis was away.')),
                ('backlog', models.PositiveIntegerField(default=0, help_text='Entries of its streams not yet stored.')),
                ('facts_lost', models.PositiveBigIntegerField(default=0, help_text='Facts trimmed from Redis before they were read.')),
                ('facts_rejected', models.PositiveBigIntegerField(default=0, help_text='Facts the site could not apply.')),
                ('logs_lost', models.PositiveBigIntegerField(default=0, help_text='Log batches trimmed before they were read.')),
                ('logs_dropped', models.PositiveBigIntegerField(default=0, help_text='Log records its buffer dropped.')),
                ('facts_cursor', models.CharField(blank=True, help_text='Last applied entry of its facts stream.', max_length=40)),
                ('logs_cursor', models.CharField(blank=True, help_text='Last stored entry of its logs stream.', max_length=40)),
                ('facts_instance', models.CharField(blank=True, max_length=32)),
                ('facts_seq', models.PositiveBigIntegerField(default=0)),
                ('logs_instance', models.CharField(blank=True, max_length=32)),
                ('logs_seq', models.PositiveBigIntegerField(default=0)),
            ],
            options={
                'ordering': ['name'],
            },
        ),
        migrations.DeleteModel(
            name='GatewayHeartbeat',
        ),
        migrations.AddField(
            model_name='robot',
            name='gateway',
            field=models.ForeignKey(null=True, on_delete=django.db.models.deletion.PROTECT, related_name='robots', to='fleet.gateway'),
        ),
        # Backwards: the column goes with the field; the gateway rows go with their table.
        migrations.RunPython(robots_to_local, migrations.RunPython.noop),
        migrations.AlterField(
            model_name='robot',
            name='gateway',
            field=models.ForeignKey(default=lifecycle_site.fleet.models.default_gateway_id, help_text="The gateway that reaches this robot's ROS domain.", on_delete=django.db.models.deletion.PROTECT, related_name='robots', to='fleet.gateway'),
        ),
    ]
