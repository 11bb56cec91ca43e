"""Close the loop: residuals, candidate effects, identification, before/after reports."""
