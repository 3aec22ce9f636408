"""Assignment, sequencing and push paths: layout + environment -> plan."""
