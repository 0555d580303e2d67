"""Service core: settings, security, logging, metrics."""
