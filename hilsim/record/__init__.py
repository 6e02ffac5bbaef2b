"""What the recorder writes: Rerun rows per message family and the viewer's default layout."""
