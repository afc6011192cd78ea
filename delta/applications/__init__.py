"""The trained avatar in use: driven by new motion (docs/applications.md)."""
