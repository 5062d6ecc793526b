"""The workspace: the one module that knows paths, schema versions, records and locks."""

from recon.io.atomic import atomic_dir, atomic_path, atomic_write_json, atomic_write_text
from recon.workspace.workspace import SCHEMA_VERSION, Workspace, WorkspaceError

__all__ = [
    "SCHEMA_VERSION",
    "Workspace",
    "WorkspaceError",
    "atomic_dir",
    "atomic_path",
    "atomic_write_json",
    "atomic_write_text",
]
