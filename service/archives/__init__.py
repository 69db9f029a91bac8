"""Uploaded dataset archives: their listing read within bounds (`listing`), then their safe
extraction into a job's folder by the rules of the profile's layout (`extraction`)."""
