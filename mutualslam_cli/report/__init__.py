"""``mslam report``: result folders → pandas → the paper's tables (Markdown, LaTeX, CSV) and figures."""
