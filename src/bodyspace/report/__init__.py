"""Reports: headless pictures of bodies (``render``) and of population statistics."""
