"""File-facing edge of greybox: loaders, writers, video readers. The core never imports this."""
