"""German pages keep the decimal point (FORMAT_MODULE_PATH): the numbers here are ROS parameter
values, rates and measurements that engineers type and read as ROS and YAML write them (0.5),
and the same numbers go into drawing coordinates, number fields and data attributes the scripts
read, which a decimal comma would break. Dates and times are written explicitly by the templates."""
DECIMAL_SEPARATOR = "."
THOUSAND_SEPARATOR = "\u202f"  # a narrow no-break space, used only where a template asks for grouping
NUMBER_GROUPING = 3
