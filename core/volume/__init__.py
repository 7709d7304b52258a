"""Volumes: from height maps (gradient and metric) and from the flow sensor."""
