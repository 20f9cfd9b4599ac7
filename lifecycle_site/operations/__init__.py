"""What an operator asks of a robot, checked once and carried out through its gateway, for every
adapter alike (the API's views, the pages' views, the ``manage.py lifecycle`` command): a
transition, a group run or a restart (the operations of ros_gateway/shared/operations.py), and
parameters. What cannot be done is a lifecycle_site.refusal.Refusal."""
