"""`rg report`: error against run time, savings, scaling and stability, as one Markdown page with plots."""
from .budgets import SECTIONS, Budgets, full_budgets, tiny_budgets  # noqa: F401
