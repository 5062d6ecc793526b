"""Cameras in one convention: OpenCV (x right, y down, z forward), column vectors,
transforms named `target_from_source`, pixel centres at +0.5."""

from recon.cameras.cameras import Cameras
from recon.cameras.rays import camera_rays, pixel_centers, project_points, unproject_pixels

__all__ = ["Cameras", "camera_rays", "pixel_centers", "project_points", "unproject_pixels"]
