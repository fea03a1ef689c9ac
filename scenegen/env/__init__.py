"""Environments that reset into stored scenes for recovery-policy training (issue 18 lands here)."""
