"""Audit records remember the gateway fact they were made from (applying it twice makes one)."""

from django.db import migrations, models


class Migration(migrations.Migration):

    dependencies = [
        ('audit', '0002_alter_transitionrecord_source_parameterrecord'),
    ]

    operations = [
        migrations.AddField(
            model_name='parameterrecord',
            name='fact_id',
            field=models.CharField(blank=True, editable=False, max_length=32, null=True, unique=True),
        ),
        migrations.AddField(
            model_name='transitionrecord',
            name='fact_id',
            field=models.CharField(blank=True, editable=False, max_length=32, null=True, unique=True),
        ),
    ]
