"""Client tools around the service: capture replay and the labeled-frame subscriber."""
