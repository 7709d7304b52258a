"""Pulmonary function values, their grading, references and interpretation."""
