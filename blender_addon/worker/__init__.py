"""What runs without bpy, off the main thread: requests and their validation, the job runner, the model cache,
generation into takes, Action names, the coverage watcher, the add-on's id and dependencies."""
