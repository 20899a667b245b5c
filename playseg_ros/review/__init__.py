"""`playseg review`: a local web page to annotate play and review a model's proposals (docs/review.md).

store.py keeps the labels (sidecar files `playseg convert` reads) and the review state; video.py encodes
each camera once as MP4; session.py is what the page shows and changes; server.py serves it over HTTP;
static/ is the page. Nothing here needs rclpy.
"""
