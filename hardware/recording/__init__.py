"""Recordings: the MCAP format, the writer, the recorder process, the reader, recover, import.

- :mod:`.format`: channels, schemas, encodings, metadata (the one place that defines a file);
- :mod:`.writer`: :class:`~.writer.RecordingWriter`, crash-safe to within its flush period;
- :mod:`.recorder`: :class:`~.recorder.Recorder`, the writer in a low-priority process fed
  through a queue that never blocks its producers;
- :mod:`.reader`: :class:`~.reader.Recording`, index-only open, seek by time, messages of
  channels in a time range, the frames and estimates decoded; unfinished files too;
- :mod:`.recover`: rewrite an unfinished file complete and indexed;
- :mod:`.rosbag_import`: ROS 1 bags and ROS 2 bags of depth images as recordings.
"""
