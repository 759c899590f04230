"""``python -m torchsph.post RUN``: see :func:`torchsph.post.summary.main`."""
from torchsph.post.summary import main

raise SystemExit(main())
