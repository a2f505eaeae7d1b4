"""`evcap report`: one self-contained HTML page of a reconstruction folder (`html.write_report`),
its images embedded as PNG data URIs (`images`) and its plots drawn as inline SVG (`svg`)."""
